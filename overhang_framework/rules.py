"""The placement rules: grid bounds, non-penetration and support.

A block may be placed at (x, layer) when it lies inside the grid, overlaps no
placed block of its layer over a positive length, and its bottom face rests on
the top face of at least one block of the layer below over a positive length.
Only the first block of a task stands on the ground (layer 0).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from overhang_framework.geometry import (
    EPS,
    GRID_HALF_WIDTH,
    MAX_LAYER,
    Action,
    Block,
    Geometry,
    overlap_length,
)


def illegal_reason(geometry: Geometry, width: float, action: Action) -> Optional[str]:
    """Why placing a block of ``width`` at ``action`` is illegal, or ``None`` if it is legal."""
    left, right, layer = action.x - width / 2, action.x + width / 2, action.layer
    if left < -GRID_HALF_WIDTH - EPS or right > GRID_HALF_WIDTH + EPS:
        return f"block spans x in [{left:g}, {right:g}], outside the grid [-{GRID_HALF_WIDTH:g}, {GRID_HALF_WIDTH:g}]"
    if not 0 <= layer <= MAX_LAYER:
        return f"layer {layer} is outside the grid (layers 0 to {MAX_LAYER})"
    if layer == 0:
        return "only the first block stands on the ground (layer 0)"
    support = 0.0
    for b in geometry.blocks:
        if b.layer == layer and overlap_length(left, right, b.left, b.right) > EPS:
            return f"block overlaps the block at x={b.x:g} in layer {layer}"
        if b.layer == layer - 1:
            support = max(support, overlap_length(left, right, b.left, b.right))
    if support <= EPS:
        return f"nothing in layer {layer - 1} supports a block at x={action.x:g}"
    return None


def is_legal(geometry: Geometry, width: float, action: Action) -> bool:
    return illegal_reason(geometry, width, action) is None


def candidate_xs(width: float, resolution: float) -> np.ndarray:
    """Every x on the grid ``k * resolution`` at which a block of ``width`` fits inside the grid."""
    limit = GRID_HALF_WIDTH - width / 2
    k = int(np.floor(limit / resolution + 1e-9))
    return np.round(np.arange(-k, k + 1) * resolution, 10)


def legal_xs(geometry: Geometry, width: float, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """The legal placements of :func:`legal_actions` as arrays ``(xs, layers)``, in the same order: layer by
    layer, each layer's x on the grid ``k * resolution`` ascending, kept where :func:`legal_mask` allows them."""
    if not geometry.blocks:
        return np.zeros(0), np.zeros(0, dtype=int)
    xs = candidate_xs(width, resolution)
    top = min(max(b.layer for b in geometry.blocks) + 1, MAX_LAYER)
    layers = np.repeat(np.arange(1, top + 1), len(xs))
    xs = np.tile(xs, top)
    ok = legal_mask(geometry, width, xs, layers)
    return xs[ok], layers[ok]


def legal_mask(geometry: Geometry, width: float, xs, layers) -> np.ndarray:
    """Whether placing a block of ``width`` at each ``(xs[i], layers[i])`` (any real x) is legal, as
    :func:`illegal_reason` decides, vectorised."""
    xs, layers = np.asarray(xs, dtype=float), np.asarray(layers, dtype=int)
    cl, cr = xs - width / 2, xs + width / 2
    ok = (cl >= -GRID_HALF_WIDTH - EPS) & (cr <= GRID_HALF_WIDTH + EPS) & (layers >= 1) & (layers <= MAX_LAYER)
    if not geometry.blocks:
        return np.zeros(len(xs), dtype=bool)
    arr = geometry.as_array()
    lefts, rights, bl = arr[:, 1] - arr[:, 0] / 2, arr[:, 1] + arr[:, 0] / 2, arr[:, 2].astype(int)
    ov = np.minimum(cr[:, None], rights[None, :]) - np.maximum(cl[:, None], lefts[None, :])
    touching = ov > EPS
    supported = (touching & (bl[None, :] == layers[:, None] - 1)).any(axis=1)
    blocked = (touching & (bl[None, :] == layers[:, None])).any(axis=1)
    return ok & supported & ~blocked


def legal_actions(geometry: Geometry, width: float, resolution: float) -> list[Action]:
    """All legal placements of a block of ``width`` with x on the grid ``k * resolution``, layer by layer."""
    xs, layers = legal_xs(geometry, width, resolution)
    return [Action(x, layer) for x, layer in zip(xs.tolist(), layers.tolist())]


def random_legal_action(geometry: Geometry, width: float, resolution: float,
                        rng: np.random.Generator) -> Optional[Action]:
    """One of :func:`legal_actions`, drawn uniformly with ``rng.integers`` (``None`` when there is none).

    The same draw as ``actions[rng.integers(len(actions))]``, without building every action.
    """
    xs, layers = legal_xs(geometry, width, resolution)
    if not len(xs):
        return None
    k = rng.integers(len(xs))
    return Action(float(xs[k]), int(layers[k]))


def place(geometry: Geometry, width: float, action: Action) -> Geometry:
    """The geometry after placing a block of ``width`` at ``action`` (no legality check)."""
    return geometry.add(Block(width, float(action.x), int(action.layer)))
