"""An adversarial check of the "stands for sure" stage: the towers it still calls standing nearest its tilt's margin.

The tiered physics (:mod:`~overhang_framework.physics.tiered`) takes a tower's
"stands" on the static model's word when the tower is in equilibrium under gravity
tilted both ways by ``stable_tilt``. Its known errors (docs/physics.md, "A wider
tilt for heavy loads on a narrow base") were heavy loads on a narrow base that
the stage called standing and the full-window reference toppled. They are rare
(13 in 290,110 sure towers at 0.02 rad), so a random sample would see none; this
module draws towers biased to that kind and keeps those nearest the margin:

1. :func:`adversarial_towers` draws seeded legal towers (the task's rules: the
   first block on the ground at ``x = 0``, every other block legal by
   :func:`overhang_framework.rules.is_legal`): mostly a ground block of 0.6,
   a column of narrow blocks, one to three heavy (1.8) blocks above layer 1,
   sometimes one beside another, and sometimes a block on top; x on the tasks'
   0.1 grid, a 0.05 grid or a 1 mm grid.
2. :func:`margin_tilts` gives, per tower, the smallest tilt at which the stage
   stops calling it standing (bisection on the stage's own tilt, batched).
3. :func:`draw_near_margin` keeps the distinct towers the stage calls standing at
   ``tilt`` but not at ``rank_tilt``, the ``n`` with the smallest such tilt.
4. :func:`replay` runs each in the reference (full window, the world config's
   PyBullet parameters); an *error* is a tower sure at ``tilt`` that falls there.
   Each error runs once more without ending at the threshold (its blocks' places
   at the window's end), and the towers of at most :data:`TASK_BLOCKS` blocks are
   counted apart.

``python -m overhang_framework.physics.adversarial --n 2000 --seed 0 --out FILE.json``
does all four and writes the counts, the parameters, the machine, the wall time,
the one-sided 95% Clopper-Pearson upper bound on the error rate among such towers
and every error tower. Everything but the timings is a function of the seed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from typing import Callable, Optional, Sequence

import numpy as np

from overhang_framework.geometry import MAX_LAYER, WIDTHS, Action, Block, Geometry
from overhang_framework.physics.pybullet_backend import PyBulletParams
from overhang_framework.physics.static_backend import StaticParams
from overhang_framework.physics.tiered import TieredBackend, TieredParams
from overhang_framework.rules import is_legal

#: x grids of the drawn towers and how often each is used: the tasks' 0.1 (the planners' and the optimum
#: search's actions), a 0.05 grid and a 1 mm grid (effectively continuous: loads at any distance from an edge).
GRIDS = ((0.1, 0.5), (0.05, 0.2), (0.001, 0.3))
#: Ground block widths and their odds: mostly the narrow base every known error stood on.
GROUND = ((0.6, 0.8), (1.2, 0.12), (1.8, 0.08))
#: Block widths of the column above the ground block, and their odds.
COLUMN = ((0.6, 0.65), (1.2, 0.35))
#: Widths of the load blocks and their odds.
LOAD = ((1.8, 0.8), (1.2, 0.2))
CONFIDENCE = 0.95
#: The most blocks a task has (six, seven for the benchmark's ``cross`` tasks): the sample's towers of at most
#: this many blocks are counted apart.
TASK_BLOCKS = 7


def _pick(rng: np.random.Generator, table) -> float:
    values, odds = zip(*table)
    return values[int(rng.choice(len(values), p=np.asarray(odds) / sum(odds)))]


def _snap(x: float, grid: float) -> float:
    return round(round(x / grid) * grid, 6) + 0.0


def _try_place(rng: np.random.Generator, geometry: Geometry, width: float, layer: int, around: float,
               reach: float, grid: float, tries: int = 8) -> Optional[Geometry]:
    """``geometry`` with a block of ``width`` at ``layer`` at an x drawn within ``reach`` of ``around`` (snapped to
    ``grid``), the first of ``tries`` draws that is legal; ``None`` when none is."""
    if not 1 <= layer <= MAX_LAYER:
        return None
    for _ in range(tries):
        x = _snap(around + float(rng.uniform(-reach, reach)), grid)
        if is_legal(geometry, width, Action(x, layer)):
            return geometry.add(Block(width, x, layer))
    return None


def adversarial_tower(rng: np.random.Generator) -> Geometry:
    """One legal tower biased to heavy loads high on a narrow base, drawn with ``rng``.

    A ground block (mostly 0.6) at ``x = 0``; a column of 0 to 3 narrow blocks (0.6 or 1.2), each within a
    third of its support's half-width of it; 1 to 3 load blocks (mostly 1.8) each on the block below, anywhere
    it still rests on it (the farther out the rarer); with odds 1/4 a block beside the top load in its layer (a
    counterweight or a second load) and with odds 1/2 a block of any width on top. Every block's x is on one
    grid of :data:`GRIDS` for the whole tower. A draw that finds no legal x for a block stops the tower there.
    """
    grid = _pick(rng, GRIDS)
    geometry = Geometry((Block(_pick(rng, GROUND), 0.0, 0),))
    top = geometry.blocks[0]
    for _ in range(int(rng.integers(0, 4))):
        width = _pick(rng, COLUMN)
        nxt = _try_place(rng, geometry, width, top.layer + 1, top.x, max(top.width / 6, grid), grid)
        if nxt is None:
            break
        geometry, top = nxt, nxt.blocks[-1]
    for _ in range(int(rng.integers(1, 4))):
        width = _pick(rng, LOAD)
        # anywhere it rests on the block below, offsets near the edge rarer: |u|^0.7 spreads them out
        reach = (top.width + width) / 2 - 0.02
        offset = float(rng.uniform(-1, 1))
        around = top.x + np.sign(offset) * abs(offset) ** 0.7 * reach
        nxt = _try_place(rng, geometry, width, top.layer + 1, around, 0.0 if grid < 0.01 else grid, grid)
        if nxt is None:
            break
        geometry, top = nxt, nxt.blocks[-1]
    if top.layer >= 2 and rng.random() < 0.25:  # a block beside the top load (is_legal: resting on the layer below)
        width = WIDTHS[int(rng.integers(3))]
        side = 1.0 if rng.random() < 0.5 else -1.0
        around = top.x + side * ((top.width + width) / 2 + float(rng.uniform(0, 0.3)))
        nxt = _try_place(rng, geometry, width, top.layer, around, 0.15, grid)
        if nxt is not None:
            geometry = nxt
    if rng.random() < 0.5:
        width = WIDTHS[int(rng.integers(3))]
        nxt = _try_place(rng, geometry, width, top.layer + 1, top.x, top.width / 2, grid)
        if nxt is not None:
            geometry = nxt
    return geometry


def adversarial_towers(n: int, seed: int = 0) -> list[Geometry]:
    """``n`` towers of :func:`adversarial_tower`, drawn from ``seed`` (the same towers for the same seed)."""
    rng = np.random.default_rng([seed, 0x7117])
    return [adversarial_tower(rng) for _ in range(n)]


def heavy_high_on_narrow(geometry: Geometry) -> bool:
    """Whether ``geometry`` is of the known errors' kind: a ground block of 0.6 and a 1.8 block at layer 2 or above."""
    ground = [b for b in geometry.blocks if b.layer == 0]
    return bool(ground) and ground[0].width == 0.6 and any(b.width == 1.8 and b.layer >= 2 for b in geometry.blocks)


def margin_tilts(backend: TieredBackend, geometries: Sequence[Geometry], low: float, high: float,
                 tolerance: float = 1e-4) -> np.ndarray:
    """Per geometry, the tilt in ``(low, high]`` at which ``backend``'s "stands for sure" stage stops passing.

    Bisection on the stage's tilt (:meth:`TieredBackend.stands_for_sure`, one tilt per tower, all towers in
    one batch per round) to within ``tolerance``: the value returned is the end of the last bracket where the
    stage fails. A tower that fails at ``low`` gets ``low``; one that passes at ``high`` gets ``inf``.
    """
    geometries = list(geometries)
    n = len(geometries)
    out = np.full(n, np.inf)
    if not n:
        return out
    at_low = backend.stands_for_sure(geometries, low)
    at_high = backend.stands_for_sure(geometries, high)
    out[~at_low] = low
    rows = np.flatnonzero(at_low & ~at_high)
    a = np.full(rows.size, float(low))  # passes
    b = np.full(rows.size, float(high))  # fails
    subset = [geometries[i] for i in rows]
    while rows.size and np.max(b - a) > tolerance:
        mid = (a + b) / 2
        ok = backend.stands_for_sure(subset, mid)
        a = np.where(ok, mid, a)
        b = np.where(ok, b, mid)
    out[rows] = b
    return out


@dataclass
class Sample:
    """Towers near the margin: ``towers`` (nearest first) with their ``tilts`` (:func:`margin_tilts`), and
    how many were drawn, distinct, sure at the tilt and near the margin (sure there, not at the rank tilt)."""

    towers: list[Geometry]
    tilts: np.ndarray
    drawn: int
    distinct: int
    sure: int
    near_margin: int
    rounds: int


def draw_near_margin(n: int, seed: int, backend: TieredBackend, rank_tilt: float, batch: int = 20000,
                     max_drawn: int = 2_000_000, tolerance: float = 1e-4,
                     progress: Optional[Callable[[int, int], None]] = None) -> Sample:
    """The ``n`` distinct towers nearest the margin of ``backend``'s stage among those drawn from ``seed``.

    Towers are drawn in rounds of ``batch`` (:func:`adversarial_tower`, one generator for every round) until
    at least ``4 n`` distinct towers near the margin (sure at the stage's tilt, not at ``rank_tilt``) are in
    hand, or ``max_drawn`` were drawn; the ``n`` with the smallest :func:`margin_tilts` are kept (ties by
    canonical key). ``progress(drawn, near)`` is called after each round.
    """
    tilt = backend.tiers.stable_tilt
    if not rank_tilt > tilt:
        raise ValueError(f"rank_tilt must be larger than the stage's tilt {tilt}, got {rank_tilt}")
    rng = np.random.default_rng([seed, 0x7117])
    seen: set = set()
    near: dict = {}
    drawn = sure = rounds = 0
    while drawn < max_drawn and len(near) < 4 * n:
        towers = []
        for _ in range(min(batch, max_drawn - drawn)):
            g = adversarial_tower(rng)
            drawn += 1
            h = hash(g.key)  # the key's hash: a million keys would take too much memory
            if h not in seen:
                seen.add(h)
                towers.append(g)
        rounds += 1
        t = margin_tilts(backend, towers, tilt, rank_tilt, tolerance)
        sure += int(np.sum(t > tilt))
        for g, v in zip(towers, t):
            if tilt < v <= rank_tilt:
                near[g.key] = (float(v), g)
        if progress:
            progress(drawn, len(near))
    ranked = sorted(near.items(), key=lambda kv: (kv[1][0], kv[0]))[:n]
    return Sample([g for _, (_, g) in ranked], np.array([v for _, (v, _) in ranked]), drawn, len(seen), sure,
                  len(near), rounds)


def replay(towers: Sequence[Geometry], params: PyBulletParams, workers: int = 1, chunk: int = 50,
           progress: Optional[Callable[[int], None]] = None) -> tuple[np.ndarray, np.ndarray]:
    """The reference's verdicts of ``towers`` and how far their farthest-moved block was when each run ended (m):
    full-window PyBullet
    (``early_stop`` off; a run ends early only once a block has passed the threshold, which is final), one
    process or a pool of ``workers``. ``progress(k)`` after every ``k`` towers."""
    params = replace(params, early_stop=False)
    stable = np.zeros(len(towers), dtype=bool)
    moved = np.zeros(len(towers))
    if workers > 1:
        from overhang_framework.physics.pool import PyBulletPool

        runner = PyBulletPool(workers, params=params, early_stop=False)
        check = runner.check_batch
    else:
        from overhang_framework.physics.pybullet_backend import PyBulletSimulator

        runner = PyBulletSimulator(params)
        check = lambda gs: [runner.check(g, early_stop=False) for g in gs]  # noqa: E731
    try:
        for start in range(0, len(towers), chunk):
            outcomes = check(list(towers[start:start + chunk]))
            for i, o in enumerate(outcomes, start):
                stable[i], moved[i] = o.stable, o.displacement
            if progress:
                progress(len(outcomes))
    finally:
        runner.close()
    return stable, moved


def upper_bound(errors: int, n: int, confidence: float = CONFIDENCE) -> float:
    """The one-sided Clopper-Pearson upper bound on a rate with ``errors`` in ``n`` (``1 - 0.05 ** (1 / n)``
    for no error at 95%)."""
    if n <= 0:
        return 1.0
    if errors >= n:
        return 1.0
    from scipy.stats import beta

    return float(beta.ppf(confidence, errors + 1, n - errors))


def world_params() -> tuple[TieredParams, StaticParams, PyBulletParams]:
    """The tiered physics' parameters as the world config (``conf/world/overhang.yaml``) sets them."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config

    world = OmegaConf.to_container(compose_config().world, resolve=True)
    return (TieredParams(**world.get("tiered", {})), StaticParams(**world.get("static", {})),
            PyBulletParams(**world.get("pybullet", {})))


def machine() -> str:
    """The machine a figure was measured on: architecture, cores, Python, the load average at the end."""
    load = ""
    if hasattr(os, "getloadavg"):
        load = ", load average {:.1f}".format(os.getloadavg()[0])
    return (f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_implementation()} "
            f"{platform.python_version()}{load}")


def tower_text(geometry: Geometry) -> str:
    """``(w,x,layer) ...`` as docs/physics.md writes towers."""
    return " ".join(f"({b.width:g},{b.x:g},{b.layer})" for b in geometry.blocks)


def composition(towers: Sequence[Geometry]) -> dict:
    """What the towers are made of: shares with a ground block of 0.6, with a 1.8 block at layer >= 2, of
    both (the known errors' kind), and the counts by number of blocks and by top layer."""
    n = max(len(towers), 1)
    ground = [next(b.width for b in g.blocks if b.layer == 0) for g in towers]
    return {
        "ground_0.6": sum(w == 0.6 for w in ground) / n,
        "heavy_at_layer_2_plus": sum(any(b.width == 1.8 and b.layer >= 2 for b in g.blocks) for g in towers) / n,
        "heavy_high_on_narrow": sum(heavy_high_on_narrow(g) for g in towers) / n,
        "blocks": {str(k): sum(len(g) == k for g in towers) for k in sorted({len(g) for g in towers})},
        "top_layer": {str(k): sum(max(b.layer for b in g.blocks) == k for g in towers)
                      for k in sorted({max(b.layer for b in g.blocks) for g in towers})},
        "on_0.1_grid": sum(all(abs(b.x * 10 - round(b.x * 10)) < 1e-6 for b in g.blocks) for g in towers) / n,
    }


def run(n: int = 2000, seed: int = 0, rank_tilt: float = 0.06, tilt: Optional[float] = None, workers: int = 1,
        batch: int = 20000, max_drawn: int = 2_000_000, quiet: bool = False) -> dict:
    """Draw, rank and replay (the module docstring); the JSON object the command writes."""
    from overhang_framework.progress import progress_bar

    start = time.perf_counter()
    tiered, static, pybullet = world_params()
    if tilt is not None:
        tiered = replace(tiered, stable_tilt=tilt)
    backend = TieredBackend(tiered, static=static, pybullet=pybullet)
    with progress_bar(total=4 * n, desc="near the margin", unit="tower", disable=quiet) as bar:
        def drew(drawn, near):
            bar.update(min(near, 4 * n) - bar.n)
            bar.set_postfix_str(f"{drawn:,} drawn")

        sample = draw_near_margin(n, seed, backend, rank_tilt, batch=batch, max_drawn=max_drawn, progress=drew)
    drawn_s = time.perf_counter() - start
    with progress_bar(total=len(sample.towers), desc="reference", unit="tower", disable=quiet) as bar:
        stands, moved = replay(sample.towers, backend.reference_params, workers=workers, progress=bar.update)
    errors = [i for i in range(len(sample.towers)) if not stands[i]]
    kept = len(sample.towers)
    # each error once more with the run not ended at the threshold: where its blocks are at the window's end
    ends = replay([sample.towers[i] for i in errors], replace(backend.reference_params, stop_on_fall=False))[1]
    small = [i for i, g in enumerate(sample.towers) if len(g) <= TASK_BLOCKS]
    small_errors = sum(not stands[i] for i in small)
    wall = time.perf_counter() - start
    return {
        "command": "python -m overhang_framework.physics.adversarial",
        "seed": seed,
        "n": n,
        "stable_tilt": tiered.stable_tilt,
        "rank_tilt": rank_tilt,
        "drawn": sample.drawn,
        "distinct": sample.distinct,
        "sure": sample.sure,
        "near_margin": sample.near_margin,
        "kept": kept,
        "reference_stands": int(np.sum(stands)),
        "errors": len(errors),
        "confidence": CONFIDENCE,
        "error_rate_upper": upper_bound(len(errors), kept),
        "task_sized": {"blocks_at_most": TASK_BLOCKS, "kept": len(small), "errors": int(small_errors),
                       "error_rate_upper": upper_bound(int(small_errors), len(small))},
        "margin_tilt": {"min": float(sample.tilts.min()) if kept else None,
                        "median": float(np.median(sample.tilts)) if kept else None,
                        "max": float(sample.tilts.max()) if kept else None},
        "largest_displacement_standing": float(moved[stands].max()) if stands.any() else None,
        "composition": composition(sample.towers),
        "error_towers": [{"tower": tower_text(sample.towers[i]), "blocks": len(sample.towers[i]),
                          "margin_tilt": float(sample.tilts[i]), "displacement": float(moved[i]),
                          "displacement_end_of_window": float(end)} for i, end in zip(errors, ends)],
        "nearest": [{"tower": tower_text(g), "margin_tilt": float(v), "displacement": float(d)}
                    for g, v, d in list(zip(sample.towers, sample.tilts, moved))[:10]],
        "params": {"tiered": asdict(tiered), "static": asdict(static), "reference": asdict(backend.reference_params)},
        "workers": workers,
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "draw_seconds": drawn_s,
        "wall_time": wall,
    }


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m overhang_framework.physics.adversarial",
        description="Draw towers biased to heavy loads on a narrow base, keep the N the tiered physics' "
                    "\"stands for sure\" stage still calls standing nearest its tilt's margin, replay them in the "
                    "full-window reference and count its errors (docs/physics.md).")
    ap.add_argument("--n", type=int, default=2000, help="towers kept and replayed (default 2000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the drawn towers (default 0)")
    ap.add_argument("--out", required=True, help="the JSON file to write (written atomically)")
    ap.add_argument("--rank-tilt", type=float, default=0.06,
                    help="keep towers the stage no longer calls standing at this tilt, rad (default 0.06)")
    ap.add_argument("--tilt", type=float, default=None,
                    help="the stage's tilt, rad (default: world.tiered.stable_tilt of the world config)")
    ap.add_argument("--workers", type=int, default=1, help="reference processes (default 1)")
    ap.add_argument("--batch", type=int, default=20000, help="towers drawn per round (default 20000)")
    ap.add_argument("--max-drawn", type=int, default=2_000_000, help="stop drawing after this many (default 2000000)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    problems = []
    for name in ("n", "batch", "max_drawn", "workers"):
        if getattr(args, name) < 1:
            problems.append(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    if args.seed < 0:
        problems.append(f"--seed must be >= 0, got {args.seed}")
    if args.tilt is not None and not 0 <= args.tilt < np.pi / 4:
        problems.append(f"--tilt must be in [0, pi/4) rad, got {args.tilt}")
    if not 0 < args.rank_tilt < np.pi / 4:
        problems.append(f"--rank-tilt must be in (0, pi/4) rad, got {args.rank_tilt}")
    if problems:
        print(f"error: {problems[0]}", file=sys.stderr)
        return 2
    from overhang_framework.results import atomic_write_json

    try:
        result = run(args.n, args.seed, args.rank_tilt, args.tilt, args.workers, args.batch, args.max_drawn,
                     args.quiet)
    except ValueError as err:  # a rank tilt not above the stage's tilt, a bad world config value
        print(f"error: {err}", file=sys.stderr)
        return 2
    atomic_write_json(args.out, result)
    print(f"{result['kept']} towers nearest the margin (of {result['drawn']:,} drawn), {result['errors']} errors; "
          f"95% upper bound on the error rate {result['error_rate_upper']:.2%}; of at most {TASK_BLOCKS} blocks: "
          f"{result['task_sized']['kept']}, {result['task_sized']['errors']} errors; {result['wall_time']:.0f} s; "
          f"written to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
