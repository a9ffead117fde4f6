"""Does a verdict depend on the order a tower's blocks are listed in? ``python -m overhang_framework.bench.order``.

The full-window reference simulates a tower's blocks in canonical order
(:mod:`overhang_framework.physics.pybullet_backend`); the order they are listed in
stays reachable for this comparison (``PyBulletSimulator._listed_order``). In one
run, with the two orders side by side:

* **permutations**: towers of the ``edge`` family (a load passing exactly through
  a support's edge), each asked with four orders of its block list: how many get
  more than one verdict;
* **main job** (``--main-job``): the default main job, ``python -m
  overhang_framework`` composed in this process, run once per order: its reference
  checks, how many of them the other order decides otherwise, its reward and
  reference-run count, and the episodes whose placements differ;
* **log** (``--log FILE``): every candidate tower of every decision of a behaviour
  log, listed as logged (the tower before, then the block), and every placed tower:
  how many reach the reference, and how many of those the canonical order decides
  otherwise;
* **speed**: full-window checks of towers with shuffled block lists (random, edge
  and indeterminate families), each in both orders, interleaved in one process.

It prints a summary and, as its last line, one JSON object with the figures;
``--out FILE`` writes that object too (atomically).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import Block, Geometry, canonical_order
from overhang_framework.physics.pybullet_backend import PyBulletParams, PyBulletSimulator
from overhang_framework.progress import progress_bar
from overhang_framework.results import atomic_write_json

ORDERS = {True: "listed", False: "canonical"}


def _listing(geometry: Geometry) -> list:
    return [[b.width, round(b.x, 6), b.layer] for b in geometry.blocks]


def _in_canonical_order(geometry: Geometry) -> bool:
    order = canonical_order(geometry.blocks)
    return order == sorted(order)


@contextmanager
def engine_order(listed: bool, record: Optional[list] = None):
    """Inside the block, every :class:`PyBulletSimulator` of this process simulates in the listed order
    (``listed``) or in canonical order; ``record`` (a list) collects ``(geometry, gravity, friction,
    early_stop, params, stable)`` for every check."""
    cls = PyBulletSimulator
    saved_flag, saved_check = cls._listed_order, cls.check

    def check(self, geometry, gravity=None, friction=None, early_stop=None):
        out = saved_check(self, geometry, gravity, friction, early_stop)
        record.append((geometry, gravity, friction, early_stop, self.params, bool(out.stable)))
        return out

    cls._listed_order = listed
    if record is not None:
        cls.check = check
    try:
        yield
    finally:
        cls._listed_order, cls.check = saved_flag, saved_check


def replay(checks: Sequence[tuple], listed: bool) -> dict:
    """Each distinct check of ``checks`` (made in order ``listed``) simulated in the other order.

    Returns the counts (checks, distinct listings, listings not in canonical order) and the listings
    whose verdict moved, with both verdicts.
    """
    distinct: dict = {}
    for geometry, gravity, friction, early_stop, params, stable in checks:
        key = (repr(geometry.blocks), None if gravity is None else tuple(gravity),
               None if friction is None else tuple(friction), early_stop, params)
        distinct.setdefault(key, (geometry, gravity, friction, early_stop, params, stable))
    sims: dict = {}
    moved = []
    for geometry, gravity, friction, early_stop, params, stable in distinct.values():
        sim = sims.get(params)
        if sim is None:
            sim = sims[params] = PyBulletSimulator(params)
            sim._listed_order = not listed
        other = sim.check(geometry, gravity, friction, early_stop=early_stop).stable
        if other != stable:
            verdicts = {ORDERS[listed]: stable, ORDERS[not listed]: bool(other)}
            moved.append({"blocks": _listing(geometry), **{k: verdicts[k] for k in ORDERS.values()}})
    for sim in sims.values():
        sim.close()
    return {"checks": len(checks), "distinct": len(distinct),
            "not_in_canonical_order": sum(not _in_canonical_order(d[0]) for d in distinct.values()),
            "moved": len(moved), "fall_to_stand": sum(not m["listed"] and m["canonical"] for m in moved),
            "stand_to_fall": sum(m["listed"] and not m["canonical"] for m in moved), "moved_towers": moved}


def _orders(n: int, rng: np.random.Generator, k: int = 3) -> list[tuple]:
    return list(dict.fromkeys([tuple(range(n))] + [tuple(int(i) for i in rng.permutation(n)) for _ in range(k)]))


def permutations(n: int = 100, seed: int = 1, quiet: bool = False) -> dict:
    """``n`` towers of the ``edge`` family (``seed``), each in its listed order and three shuffles: in each
    engine order, how many towers get more than one verdict."""
    from overhang_framework.physics.towers import family_towers

    towers = family_towers("edge", n, seed=seed)
    rng = np.random.default_rng([seed, 7])
    asked = [[Geometry(tuple(g.blocks[i] for i in o)) for o in _orders(len(g), rng)] for g in towers]
    sim = PyBulletSimulator(PyBulletParams())
    split = {}
    for listed in (True, False):
        sim._listed_order = listed
        bar = progress_bar(asked, desc=f"permutations, {ORDERS[listed]} order", disable=quiet, leave=False,
                           file=sys.stderr)
        split[ORDERS[listed]] = sum(len({sim.check(t).stable for t in lists}) > 1 for lists in bar)
    sim.close()
    return {"family": "edge", "seed": seed, "towers": n, "orders_per_tower": 4,
            "towers_with_two_verdicts": split}


def main_job(overrides: Sequence[str] = ()) -> dict:
    """The default main job (with ``overrides``) run once in each engine order, in this process."""
    from overhang_framework.app import run
    from overhang_framework.config import compose_config

    runs = {}
    for listed in (True, False):
        checks: list = []
        with tempfile.TemporaryDirectory() as tmp, engine_order(listed, checks):
            out = Path(tmp) / "run"
            summary = run(compose_config(list(overrides)), out)
            episodes = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines() if line]
        placements = {(e["task_id"], e["repeat"]): [(s["x"], s["layer"], s["stable"]) for s in e["steps"]]
                      for e in episodes}
        stats = summary.get("world_stats", {}).get("cache", {})
        runs[ORDERS[listed]] = {
            "reward_mean": summary["reward_mean"], "reward_sem": summary["reward_sem"],
            "reference_runs": stats.get("backend", {}).get("reference"),
            "rewards": {e["task_id"]: e["reward"] for e in episodes},
            "placements": placements, "replay": replay(checks, listed),
        }
    a, b = runs["listed"], runs["canonical"]
    differ = sorted(t for (t, r) in a["placements"] if a["placements"][(t, r)] != b["placements"].get((t, r)))
    for r in runs.values():
        r.pop("placements")
    return {"overrides": list(overrides), **runs, "episodes_differ": differ,
            "rewards_differ": {t: [a["rewards"][t], b["rewards"][t]] for t in differ}}


def log_candidates(path: str, quiet: bool = False) -> dict:
    """Every candidate and placed tower of the behaviour log at ``path``, listed as logged: how many reach
    the reference under the default (tiered) physics, and how many of those move in canonical order."""
    from overhang_framework import rules
    from overhang_framework.behaviour.log import read_log, records_of
    from overhang_framework.interfaces import State
    from overhang_framework.physics.tiered import TieredBackend
    from overhang_framework.plugins import Registry

    world = Registry().create("world", {"name": "overhang"})
    candidates: dict = {}
    placed: dict = {}
    for r in records_of(read_log(path)):
        before = Geometry.from_tuples(r["tower_before"])
        for action in world.legal_actions(State(before, (r["width"],))):
            tower = rules.place(before, r["width"], action)
            candidates.setdefault(tower.key, tower)
        if r.get("x") is not None:  # a timeout places nothing
            tower = before.add(Block(float(r["width"]), float(r["x"]), int(r["layer"])))
            placed.setdefault(tower.key, tower)
    tiered = TieredBackend()
    out = {"log": str(path)}
    for name, towers in (("candidates", list(candidates.values())), ("placed", list(placed.values()))):
        band = [t for t, s in zip(towers, tiered.classify(towers)) if s < 0]
        checks: list = []
        sim = PyBulletSimulator(tiered.reference_params)
        with engine_order(True, checks):
            for t in progress_bar(band, desc=f"log {name}", disable=quiet, leave=False, file=sys.stderr):
                sim.check(t)
        sim.close()
        out[name] = {"towers": len(towers), "reference": len(band), **replay(checks, listed=True)}
    return out


def speed(n: int = 200, seed: int = 0, quiet: bool = False) -> dict:
    """Full-window checks of ``n`` random towers and ``n // 4`` each of the edge and indeterminate families,
    their block lists shuffled, each checked in both orders (which first alternates at random)."""
    from overhang_framework.physics.towers import family_towers, random_towers

    rng = np.random.default_rng(seed)
    towers = random_towers(n, seed=seed) + family_towers("edge", n // 4, seed=seed) \
        + family_towers("indeterminate", n // 4, seed=seed)
    towers = [Geometry(tuple(g.blocks[i] for i in rng.permutation(len(g)))) for g in towers]
    sim = PyBulletSimulator(PyBulletParams())
    seconds = dict.fromkeys(ORDERS.values(), 0.0)
    steps = dict.fromkeys(ORDERS.values(), 0)
    stand = dict.fromkeys(ORDERS.values(), 0)
    for g in progress_bar(towers, desc="speed", disable=quiet, leave=False, file=sys.stderr):
        for listed in ((True, False) if rng.random() < 0.5 else (False, True)):
            sim._listed_order = listed
            t = time.perf_counter()
            outcome = sim.check(g)
            seconds[ORDERS[listed]] += time.perf_counter() - t
            steps[ORDERS[listed]] += outcome.steps
            stand[ORDERS[listed]] += outcome.stable
    sim.close()
    m = len(towers)
    g7 = random_towers(1, seed=3, min_blocks=7)[0].blocks
    t = time.perf_counter()
    for _ in range(10_000):
        canonical_order(g7)
    return {"towers": m, "ms_per_check": {k: 1e3 * v / m for k, v in seconds.items()},
            "steps_per_check": {k: v / m for k, v in steps.items()}, "stand": stand,
            "canonical_order_us_7_blocks": 1e6 * (time.perf_counter() - t) / 10_000}


def summary(f: dict) -> str:
    """A few readable lines of :func:`main`'s figures."""
    lines = []
    p = f.get("permutations")
    if p:
        s = p["towers_with_two_verdicts"]
        lines.append(f"permutations: {p['towers']} {p['family']} towers (seed {p['seed']}), {p['orders_per_tower']} "
                     f"orders each: two verdicts for {s['listed']} simulated as listed, {s['canonical']} in canonical order")
    j = f.get("main_job")
    if j:
        for name in ORDERS.values():
            r = j[name]
            lines.append(f"main job, {name} order: reward {r['reward_mean']:.3f} ± {r['reward_sem']:.3f}, "
                         f"{r['reference_runs']} reference runs")
        rp = j["canonical"]["replay"]
        lines.append(f"main job: {rp['distinct']} towers asked of the reference ({rp['not_in_canonical_order']} not in "
                     f"canonical order); verdicts moved: {rp['moved']} ({rp['fall_to_stand']} fall -> stand, "
                     f"{rp['stand_to_fall']} stand -> fall) in canonical order; "
                     f"{j['listed']['replay']['moved']} of the listed order's run move the other way")
        lines.append(f"main job: episodes that differ: {len(j['episodes_differ'])} "
                     + ", ".join(f"{t} {a:g} -> {b:g}" for t, (a, b) in j["rewards_differ"].items()))
    lg = f.get("log")
    if lg:
        for name in ("candidates", "placed"):
            r = lg[name]
            lines.append(f"log {name}: {r['towers']} towers, {r['reference']} reach the reference "
                         f"({r['not_in_canonical_order']} listed otherwise than canonically); verdicts moved: "
                         f"{r['moved']} ({r['fall_to_stand']} fall -> stand, {r['stand_to_fall']} stand -> fall)")
    s = f.get("speed")
    if s:
        ms, st = s["ms_per_check"], s["steps_per_check"]
        lines.append(f"speed: {s['towers']} towers, full window: {ms['listed']:.2f} ms per check listed, "
                     f"{ms['canonical']:.2f} ms canonical ({st['listed']:.0f} and {st['canonical']:.0f} steps); "
                     f"canonical_order of 7 blocks {s['canonical_order_us_7_blocks']:.1f} us")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.order",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--edge", type=int, default=100, help="edge towers for the permutations (default 100, 0 to skip)")
    ap.add_argument("--edge-seed", type=int, default=1)
    ap.add_argument("--main-job", action="store_true", help="run the default main job in both orders")
    ap.add_argument("--log", help="a behaviour log whose candidate and placed towers to check in both orders")
    ap.add_argument("--speed", type=int, default=200,
                    help="random towers for the speed comparison, plus a quarter as many edge and indeterminate "
                         "towers each (default 200, 0 to skip)")
    ap.add_argument("--out", help="also write the JSON figures to this file")
    ap.add_argument("--quiet", action="store_true", help="no progress bars or summary")
    args = ap.parse_args(argv)
    for name in ("edge", "speed"):
        if getattr(args, name) < 0:
            ap.error(f"--{name} must be a whole number >= 0, got {getattr(args, name)}")
    figures: dict = {}
    if args.edge:
        figures["permutations"] = permutations(args.edge, args.edge_seed, args.quiet)
    if args.main_job:
        figures["main_job"] = main_job(["progress=false"])
    if args.log:
        if not Path(args.log).is_file():
            ap.error(f"--log {args.log}: no such file")
        figures["log"] = log_candidates(args.log, args.quiet)
    if args.speed:
        figures["speed"] = speed(args.speed, quiet=args.quiet)
    if args.out:
        atomic_write_json(args.out, figures)
    if not args.quiet:
        print(summary(figures))
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
