"""Seeded random towers, towers at the edge of stability, and episode-like questions: for the physics' checks, the CNN's data and the benchmarks.

Two sets are generated here:

* :func:`random_towers` -- random *legal* towers of ``min_blocks`` to
  ``max_blocks`` blocks. The first block (random width) stands on the ground at
  ``x = 0``; every further block gets a random width and a uniformly random legal
  action (:func:`overhang_framework.rules.legal_actions` at ``resolution``).
  Legal does not mean stable: many of these towers fall.
* :func:`near_critical_towers` -- towers whose last block sits within
  ``window`` of the x at which a reference verdict flips. The flip is located by
  bisection with the reference, batched over all towers so that a process pool
  can serve the reference.

and one set of questions:

* :func:`episode_questions` -- episode-like prediction questions: a tower whose
  every prefix stands (by a reference) and one more block at a random legal
  action, as a planner would score it.

Everything is deterministic for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from overhang_framework.geometry import EPS, GRID_HALF_WIDTH, WIDTHS, Action, Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.rules import place, random_legal_action

Verdicts = Callable[[Sequence[Geometry]], np.ndarray]
"""A batched stability reference: geometries in, boolean array out."""


CONTINUOUS = 0.001
"""The x step used for ``resolution=None`` (effectively continuous positions)."""


def random_tower(rng: np.random.Generator, n_blocks: int, resolution: Optional[float] = 0.05) -> Geometry:
    """One random legal tower of ``n_blocks`` blocks drawn with ``rng``.

    Actions are drawn uniformly from the legal actions on the x grid
    ``k * resolution`` (``None``: a 0.001 grid, effectively continuous).

    Raises ``RuntimeError`` if some block has no legal action (cannot happen on
    the 8 x 8 grid for up to 7 blocks, kept as a guard).
    """
    width = WIDTHS[rng.integers(len(WIDTHS))]
    geometry = Geometry((Block(width, 0.0, 0),))
    for _ in range(n_blocks - 1):
        width = WIDTHS[rng.integers(len(WIDTHS))]
        action = random_legal_action(geometry, width, CONTINUOUS if resolution is None else resolution, rng)
        if action is None:
            raise RuntimeError(f"no legal action for a block of width {width} on {geometry.key}")
        geometry = place(geometry, width, action)
    return geometry


def random_towers(n: int, seed: int = 0, min_blocks: int = 2, max_blocks: int = 7,
                  resolution: Optional[float] = 0.05) -> list[Geometry]:
    """``n`` random legal towers; block counts uniform in ``[min_blocks, max_blocks]``."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(min_blocks, max_blocks + 1, size=n)
    return [random_tower(rng, int(k), resolution) for k in counts]


def with_last_x(geometry: Geometry, x: float) -> Geometry:
    """``geometry`` with its last block moved to ``x`` (same width and layer)."""
    last = geometry.blocks[-1]
    return Geometry(geometry.blocks[:-1] + (Block(last.width, float(x), last.layer),))


def last_block_interval(geometry: Geometry, min_support: float = 0.01) -> tuple[float, float]:
    """The x interval, containing the last block's current x, along which it stays legal.

    Legal here means: inside the grid, no overlap with another block of its
    layer, and at least ``min_support`` of contact with some block of the layer
    below (or anywhere on the ground for layer 0).
    """
    last = geometry.blocks[-1]
    w, x0, layer = last.width, last.x, last.layer
    lo, hi = -GRID_HALF_WIDTH + w / 2, GRID_HALF_WIDTH - w / 2
    others = geometry.blocks[:-1]
    for b in others:
        if b.layer == layer:
            if b.x <= x0:
                lo = max(lo, b.right + w / 2)
            else:
                hi = min(hi, b.left - w / 2)
    if layer > 0:
        supports = sorted((b.left - w / 2 + min_support, b.right + w / 2 - min_support)
                          for b in others if b.layer == layer - 1)
        merged: list[list[float]] = []
        for a, c in supports:
            if merged and a <= merged[-1][1] + EPS:
                merged[-1][1] = max(merged[-1][1], c)
            else:
                merged.append([a, c])
        for a, c in merged:
            if a - EPS <= x0 <= c + EPS:
                lo, hi = max(lo, a), min(hi, c)
                break
        else:
            return (x0, x0)
    return (min(lo, x0), max(hi, x0))


@dataclass(frozen=True)
class CriticalTower:
    """A near-critical tower and how it was made.

    ``flip_x`` is where the reference verdict changes (to within ``tolerance``
    of the bisection), ``offset`` how far the last block was moved from it.
    """

    geometry: Geometry
    base: Geometry
    flip_x: float
    offset: float


def find_flips(towers: Sequence[Geometry], reference: Verdicts, tolerance: float = 0.002,
               progress: Optional[Callable[[int], None]] = None) -> list[Optional[float]]:
    """For each tower, an x of its last block where ``reference`` changes its verdict.

    The bracket is the block's current x and whichever end of its legal
    interval (:func:`last_block_interval`) has the other verdict (the farther
    end when both do); it is then bisected until shorter than ``tolerance``.
    ``None`` for towers whose verdict is the same at all three points. The
    reference is chaotic within millimetres of its flip (docs/physics.md), so
    the x found is one sample of that band, not the only place where the
    verdict changes.
    ``progress`` is called with the number of reference checks done per round.
    """
    n = len(towers)
    intervals = [last_block_interval(g) for g in towers]
    x0 = np.array([g.blocks[-1].x for g in towers])
    probe = []
    for g, (lo, hi) in zip(towers, intervals):
        probe.extend([g, with_last_x(g, lo), with_last_x(g, hi)])
    v = np.asarray(reference(probe), dtype=bool).reshape(n, 3)
    if progress:
        progress(len(probe))
    a = x0.copy()
    b = np.full(n, np.nan)
    va = v[:, 0]
    for i, (lo, hi) in enumerate(intervals):
        ends = [(abs(e - x0[i]), e) for e, ve in ((lo, v[i, 1]), (hi, v[i, 2])) if ve != v[i, 0]]
        if ends:
            b[i] = max(ends)[1]
    active = np.flatnonzero(~np.isnan(b))
    while active.size:
        active = active[np.abs(b[active] - a[active]) > tolerance]
        if not active.size:
            break
        mids = (a[active] + b[active]) / 2
        vm = np.asarray(reference([with_last_x(towers[i], m) for i, m in zip(active, mids)]), dtype=bool)
        if progress:
            progress(len(active))
        same = vm == va[active]
        a[active[same]] = mids[same]
        b[active[~same]] = mids[~same]
    return [None if np.isnan(b[i]) else float((a[i] + b[i]) / 2) for i in range(n)]


def near_critical_towers(n: int, reference: Verdicts, seed: int = 0, window: float = 0.05,
                         min_blocks: int = 2, max_blocks: int = 7, resolution: Optional[float] = 0.05,
                         tolerance: float = 0.002, max_rounds: int = 20,
                         progress: Optional[Callable[[int], None]] = None) -> list[CriticalTower]:
    """``n`` towers whose last block is within ``window`` of a flip of ``reference``.

    Random towers (:func:`random_towers`) are drawn in rounds; towers with no
    flip along their last block's legal interval are skipped. The last block of
    each kept tower is moved to ``flip_x + U(-window, window)``, clipped to its
    legal interval. Fewer than ``n`` towers come back only if ``max_rounds``
    rounds did not find enough flips.
    """
    rng = np.random.default_rng(seed)
    found: list[CriticalTower] = []
    for round_ in range(max_rounds):
        if len(found) >= n:
            break
        want = max(8, 3 * (n - len(found)))
        batch = random_towers(want, seed=int(rng.integers(2**31)), min_blocks=min_blocks,
                              max_blocks=max_blocks, resolution=resolution)
        flips = find_flips(batch, reference, tolerance=tolerance, progress=progress)
        for g, fx in zip(batch, flips):
            if fx is None or len(found) >= n:
                continue
            lo, hi = last_block_interval(g)
            offset = float(rng.uniform(-window, window))
            x = float(np.clip(fx + offset, lo, hi))
            found.append(CriticalTower(with_last_x(g, x), g, fx, x - fx))
    return found


@dataclass(frozen=True)
class Question:
    """One prediction to make: ``state`` (a standing tower and the next width), ``action``, verdict.

    ``n_blocks`` is the number of blocks after the action, ``index`` the
    question's number among those of its ``n_blocks``, ``stable`` the
    reference verdict of the tower after the action.
    """

    n_blocks: int
    index: int
    state: State
    action: Action
    stable: bool

    @property
    def geometry(self) -> Geometry:
        return place(self.state.geometry, self.state.next_width, self.action)


def episode_questions(reference: Verdicts, per_height: int, seed: int = 0, min_blocks: int = 2,
                      max_blocks: int = 7, resolution: float = 0.1, oversample: int = 2,
                      progress: Optional[Callable[[int], None]] = None) -> list[Question]:
    """``per_height`` questions for every number of blocks in ``[min_blocks, max_blocks]``.

    Level ``n`` extends ``oversample * per_height`` towers drawn with
    replacement from the standing towers of level ``n - 1`` (level 1: a ground
    block of random width at ``x = 0``), each by a block of random width at a
    uniformly random legal action on the ``resolution`` grid; the first
    ``per_height`` extensions are the questions, and every standing extension
    joins the pool for level ``n + 1``. ``progress`` is called with the number
    of reference checks of each level.

    Raises ``RuntimeError`` when no tower of a level below ``max_blocks`` stands.
    """
    rng = np.random.default_rng(seed)
    pool = [Geometry((Block(WIDTHS[rng.integers(len(WIDTHS))], 0.0, 0),)) for _ in range(per_height)]
    questions: list[Question] = []
    for n in range(2, max_blocks + 1):
        m = oversample * per_height
        states, actions = [], []
        for i in rng.integers(len(pool), size=m):
            width = WIDTHS[rng.integers(len(WIDTHS))]
            states.append(State(pool[i], (width,)))
            actions.append(random_legal_action(pool[i], width, resolution, rng))
        towers = [place(s.geometry, s.next_width, a) for s, a in zip(states, actions)]
        verdicts = np.asarray(reference(towers), dtype=bool)
        if progress:
            progress(len(towers))
        if n >= min_blocks:
            questions.extend(Question(n, j, states[j], actions[j], bool(verdicts[j]))
                             for j in range(per_height))
        pool = [t for t, v in zip(towers, verdicts) if v]
        if not pool and n < max_blocks:
            raise RuntimeError(f"no tower of {n} blocks stands; cannot grow to {n + 1}")
    return questions


FAMILIES = ("random", "tall_cantilever", "counterweight", "indeterminate", "edge")
"""Tower families of :func:`family_towers`."""


def _stack(rng: np.random.Generator, n_blocks: int) -> Geometry:
    """A single-support stack: every block on the block just below it, anywhere it still touches."""
    geometry = Geometry((Block(WIDTHS[rng.integers(3)], 0.0, 0),))
    for layer in range(1, n_blocks):
        below = geometry.blocks[-1]
        w = WIDTHS[rng.integers(3)]
        reach = (below.width + w) / 2 - 0.05
        x = below.x + float(rng.uniform(-reach, reach)) * float(rng.uniform(0.3, 1.0))
        geometry = geometry.add(Block(w, round(x, 3), layer))
    return geometry


def _counterweight(rng: np.random.Generator) -> Geometry:
    """A block whose own centre overhangs its support, held by a counterweight on its inner end."""
    base = Block(WIDTHS[rng.integers(1, 3)], 0.0, 0)
    side = 1.0 if rng.random() < 0.5 else -1.0
    arm = Block(1.8, side * round(base.width / 2 + float(rng.uniform(0.0, 0.5)), 3), 1)
    blocks = [base, arm]
    if rng.random() < 0.4:  # a load on the outer end too
        blocks.append(Block(0.6, round(arm.x + side * float(rng.uniform(0.2, 0.6)), 3), 2))
    w = WIDTHS[rng.integers(3)]
    inner = arm.x - side * float(rng.uniform(0.0, 0.9))
    if blocks[-1].layer == 2:
        outer = blocks[-1]
        limit = outer.x - side * (outer.width + w) / 2
        inner = min(inner, limit) if side > 0 else max(inner, limit)
    blocks.append(Block(w, round(inner, 3), 2))
    return Geometry(tuple(blocks))


def _indeterminate(rng: np.random.Generator) -> Geometry:
    """Two pillars on a base carry a bridge; one or two blocks above it; several blocks have two supports."""
    base = Block(1.8, 0.0, 0)
    wl, wr = WIDTHS[rng.integers(2)], WIDTHS[rng.integers(2)]
    xl = round(-0.9 + wl / 2 + float(rng.uniform(-0.3, 0.3)), 3)
    xr = round(0.9 - wr / 2 + float(rng.uniform(-0.3, 0.3)), 3)
    xr = max(xr, xl + (wl + wr) / 2 + 0.05)
    bridge = Block(1.8, round((xl + xr) / 2 + float(rng.uniform(-0.6, 0.6)), 3), 2)
    blocks = [base, Block(wl, xl, 1), Block(wr, xr, 1), bridge]
    for layer in range(3, 3 + int(rng.integers(1, 3))):
        below = blocks[-1]
        w = WIDTHS[rng.integers(3)]
        blocks.append(Block(w, round(below.x + float(rng.uniform(-0.6, 0.6)), 3), layer))
    return Geometry(tuple(blocks))


def _on_an_edge(geometry: Geometry) -> Optional[Geometry]:
    """``geometry`` with its last block moved so that the load on one contact below it passes
    exactly through that contact's edge, or ``None`` when no such legal placement holds the rest.

    Only for single-support chains under the last block; the candidate x values
    are tried nearest first, and kept when the rigid model with no margin
    (which accepts a load exactly on an edge) calls the tower stable.
    """
    from overhang_framework.physics.static_backend import StaticBackend

    blocks = list(geometry.blocks)
    last = blocks[-1]
    chain = []
    cur = last
    while cur.layer > 0:
        sup = [b for b in blocks[:-1] if b.layer == cur.layer - 1 and min(cur.right, b.right) - max(cur.left, b.left) > 0]
        if len(sup) != 1:
            return None
        chain.append((cur, sup[0]))
        cur = sup[0]
    options = []
    for k, (upper, lower) in enumerate(chain):
        above = [b for b in blocks[:-1] if b.layer >= upper.layer and _rests_on(blocks[:-1], b, upper)]
        m = sum(b.width for b in above)
        s = sum(b.width * b.x for b in above)
        for edge in (max(upper.left, lower.left), min(upper.right, lower.right)) if k else (lower.left, lower.right):
            options.append((m + last.width) * edge / last.width - s / last.width)
    static = StaticBackend(margin=0.0, height_margin=0.0, friction_scale=1.0)
    lo, hi = last_block_interval(geometry)
    for x in sorted(options, key=lambda v: abs(v - last.x)):
        if lo <= x <= hi:
            g = with_last_x(geometry, x)
            if static.stable(g):
                return g
    return None


def _rests_on(blocks, block: Block, upper: Block) -> bool:
    """Whether ``block`` is ``upper`` or rests, directly or not, on it (single-support chains)."""
    cur = block
    while cur.layer > upper.layer:
        sup = [b for b in blocks if b.layer == cur.layer - 1 and min(cur.right, b.right) - max(cur.left, b.left) > 0]
        if not sup:
            return False
        cur = sup[0]
    return cur == upper


def family_towers(family: str, n: int, seed: int = 0) -> list[Geometry]:
    """``n`` seeded towers of one of :data:`FAMILIES`, legal or not, before any move to a flip.

    ``random``: :func:`random_towers`; ``tall_cantilever``: single-support
    stacks of 4 to 7 blocks; ``counterweight``: a block overhanging its
    support held by a block on its inner end; ``indeterminate``: a bridge on
    two pillars with blocks above (statically indeterminate); ``edge``: random
    stacks and towers whose last block is moved so that a load passes exactly
    through a support's edge.
    """
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    if family == "random":
        return random_towers(n, seed=seed)
    out: list[Geometry] = []
    for _ in range(100 * n + 100):
        if len(out) >= n:
            break
        if family == "tall_cantilever":
            out.append(_stack(rng, int(rng.integers(4, 8))))
        elif family == "counterweight":
            out.append(_counterweight(rng))
        elif family == "indeterminate":
            out.append(_indeterminate(rng))
        elif family == "edge":
            g = _on_an_edge(_stack(rng, int(rng.integers(2, 7))))
            if g is not None:
                out.append(g)
        else:
            raise ValueError(f"unknown tower family {family!r}; allowed: {', '.join(FAMILIES)}")
    if len(out) < n:
        raise RuntimeError(f"found only {len(out)} of {n} {family} towers")
    return out
