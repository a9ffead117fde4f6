"""An example predictor plugin: a centre-of-mass-margin heuristic, with its config file.

Install it with ``pip install examples/com_margin_plugin`` and run::

    python -m overhang_framework predictor=com_margin tasks=example
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from overhang_framework.geometry import EPS, Action
from overhang_framework.hookspecs import hookimpl
from overhang_framework.interfaces import Predictor, State

__version__ = "0.1.0"


def _closure(adjacent: np.ndarray) -> np.ndarray:
    """Reflexive-transitive closure of a batch of boolean ``(K, n, n)`` relations."""
    n = adjacent.shape[-1]
    reach = (np.eye(n, dtype=bool)[None] | adjacent).astype(np.float32)
    for _ in range(max(1, int(np.ceil(np.log2(max(n, 2)))))):  # squaring doubles the paths covered
        reach = (np.matmul(reach, reach) > 0).astype(np.float32)
    return reach > 0


def com_margins(widths: np.ndarray, xs: np.ndarray, layers: np.ndarray) -> np.ndarray:
    """The centre-of-mass margin of each of a batch of towers, in metres.

    ``widths``, ``xs`` and ``layers`` are ``(K, n)`` arrays: K towers of n
    blocks each. For every block, the load is the block and everything resting
    on it, directly or indirectly (uniform density: mass is proportional to
    width). Its *support hull* runs from the leftmost to the rightmost of the
    block's contacts with the layer below (its own extent for the block on the
    ground). The block's margin is the signed distance of the load's centre of
    mass inside the hull (negative outside); the tower's margin is the
    smallest over its blocks. Blocks of one layer that share a load (a bridge
    on two posts) are checked together: their loads, merged, against the
    hull of all their contacts.
    """
    widths, xs = np.asarray(widths, dtype=float), np.asarray(xs, dtype=float)
    layers = np.asarray(layers).astype(int)
    left, right = xs - widths / 2, xs + widths / 2
    # rests[k, i, j]: block i rests on block j, over the contact [lo, hi]
    lo = np.maximum(left[:, :, None], left[:, None, :])
    hi = np.minimum(right[:, :, None], right[:, None, :])
    rests = (layers[:, :, None] == layers[:, None, :] + 1) & (hi - lo > EPS)
    ground = ~rests.any(axis=2)
    hull_left = np.where(ground, left, np.where(rests, lo, np.inf).min(axis=2))
    hull_right = np.where(ground, right, np.where(rests, hi, -np.inf).max(axis=2))
    touching = rests | np.swapaxes(rests, 1, 2)
    margin = np.full(len(widths), np.inf)
    for layer in np.unique(layers):
        above = layers >= layer
        # together[k, i, j]: i and j are joined through blocks at or above this layer
        together = _closure(touching & above[:, :, None] & above[:, None, :]) & above[:, None, :]
        mass = together @ widths[:, :, None]
        com = (together @ (widths * xs)[:, :, None] / np.maximum(mass, EPS))[..., 0]  # 0 / EPS below the layer
        base = together & (layers == layer)[:, None, :]  # the blocks of this layer in i's group
        group_left = np.where(base, hull_left[:, None, :], np.inf).min(axis=2)
        group_right = np.where(base, hull_right[:, None, :], -np.inf).max(axis=2)
        m = np.minimum(com - group_left, group_right - com)
        margin = np.minimum(margin, np.where(layers == layer, m, np.inf).min(axis=1))
    return margin


class ComMarginPredictor(Predictor):
    """P(stand) = logistic(margin / scale + bias), with ``margin`` from :func:`com_margins`.

    A heuristic, not physics: it ignores friction and side contacts, treats
    the load of a block on several supports as free to use the whole hull of
    its contacts, and ignores clamping (a block pinned by blocks above it,
    which can hold a counterweighted overhang). ``scale`` (metres) sets how
    soft the verdict is near a support's edge; ``bias`` shifts the logit.
    Deterministic: ``rng`` is not used. Vectorised over the candidate
    actions: one call scores every candidate in a few array operations.
    """

    def __init__(self, world, scale: float = 0.05, bias: float = 0.0):
        for name, value in (("scale", scale), ("bias", bias)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if scale <= 0:
            raise ValueError(f"scale must be a positive number of metres, got {scale!r}")
        self.world, self.scale, self.bias = world, float(scale), float(bias)

    def margins(self, state: State, actions: Sequence[Action]) -> np.ndarray:
        """The centre-of-mass margin of the tower after each action, in metres."""
        if not len(actions):
            return np.zeros(0)
        base = state.geometry.as_array()
        k = len(actions)
        cand = np.array([(a.x, a.layer) for a in actions], dtype=float)
        widths = np.concatenate([np.broadcast_to(base[:, 0], (k, len(base))),
                                 np.full((k, 1), float(state.next_width))], axis=1)
        xs = np.concatenate([np.broadcast_to(base[:, 1], (k, len(base))), cand[:, :1]], axis=1)
        layers = np.concatenate([np.broadcast_to(base[:, 2], (k, len(base))), cand[:, 1:]], axis=1)
        return com_margins(widths, xs, layers.astype(int))

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        logit = self.margins(state, actions) / self.scale + self.bias
        return 0.5 * (1.0 + np.tanh(0.5 * logit))  # the logistic function, without overflow


@hookimpl
def register_predictors(register):
    register("com_margin", ComMarginPredictor)


@hookimpl
def config_search_paths():
    return ["pkg://overhang_com_margin.conf"]
