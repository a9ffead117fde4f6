"""Lookahead with the world's verdicts, deferring the reference against settling first, side by side:
``python -m overhang_framework.bench.lookahead_defer``.

On decision states of the benchmark's ``test`` split (each task's start and the state after
``--placed`` placements of the myopic planner under the static physics), one lookahead decision with
the veridical predictor under the default physics (the full-window reference where the static stages
are unsure), ``planner.defer=true`` (the default) beside ``false`` (every unsure child settled before
its subtree), each from an empty verdict cache (a new world, no verdict file), alternating which goes
first (:mod:`overhang_framework.bench.sidebyside`). Prints each version's seconds and reference runs per
decision at each depth and whether every decision was the same; the last line is one JSON object
(``--out FILE`` writes it too).

    python -m overhang_framework.bench.lookahead_defer
    python -m overhang_framework.bench.lookahead_defer --tasks 12 --depths 2,3 --placed 0,1
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Optional, Sequence

import numpy as np

from overhang_framework.bench.sidebyside import ratio, side_by_side


def states(n_tasks: int, placed: Sequence[int]):
    """Decision states: the first ``n_tasks`` tasks of ``test``, after each count of ``placed`` placements."""
    from overhang_framework.benchmark.splits import split_ids, task
    from overhang_framework.interfaces import Budget
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    planner = registry.create("planner", {"name": "myopic"}, world=world)
    out = []
    for tid in split_ids("test")[:n_tasks]:
        state = world.initial_state(task(tid))
        for k in range(max(placed) + 1):
            if k in placed:
                out.append((tid, k, state))
            if state.done:
                break
            state = world.step(state, planner.plan(state, predictor, value, Budget(), np.random.default_rng(k)).action)
    return out


def decide(state, depth: int, defer: bool, seed: int = 0) -> dict:
    from overhang_framework.interfaces import Budget
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang"})
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    planner = registry.create("planner", {"name": "lookahead", "depth": depth, "defer": defer}, world=world)
    d = planner.plan(state, predictor, value, Budget(), np.random.default_rng(seed))
    runs = int(((world.stats().get("cache") or {}).get("backend") or {}).get("reference", 0))
    close = getattr(world.backend, "close", None)
    if close is not None:
        close()
    return {"action": (round(d.action.x, 6), d.action.layer), "reference_runs": runs}


def main(argv: Optional[Sequence[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.lookahead_defer",
                                 description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tasks", type=int, default=8, help="the first N tasks of test (default 8)")
    ap.add_argument("--placed", default="0,1", help="placements before each decision state (default 0,1)")
    ap.add_argument("--depths", default="2,3", help="lookahead depths (default 2,3)")
    ap.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = ap.parse_args(argv)
    try:
        placed = sorted({int(w) for w in args.placed.split(",")})
        depths = [int(w) for w in args.depths.split(",")]
    except ValueError:
        ap.error("--placed and --depths take comma-separated whole numbers")
    if args.tasks < 1 or min(placed) < 0 or min(depths) < 1:
        ap.error("--tasks and --depths take numbers >= 1, --placed numbers >= 0")
    cases = states(args.tasks, placed)
    started = time.perf_counter()
    out = {"tasks": args.tasks, "placed": placed, "states": len(cases), "depths": {}}
    for depth in depths:
        print(f"depth {depth}: {len(cases)} states, each from an empty verdict cache", flush=True)
        figures = side_by_side(cases, {"deferred": lambda c, d=depth: decide(c[2], d, True),
                                       "settled first": lambda c, d=depth: decide(c[2], d, False)},
                               label=lambda c: f"{c[0]} after {c[1]}", quiet=False)
        row = {"same_decisions": sum(a["action"] == b["action"] for a, b in
                                     zip(figures["versions"]["deferred"]["results"],
                                         figures["versions"]["settled first"]["results"]))}
        for name in ("deferred", "settled first"):
            v = figures["versions"][name]
            runs = [r["reference_runs"] for r in v["results"]]
            row[name] = {"seconds_per_decision": v["total"] / len(cases),
                         "median_seconds": float(np.median(v["seconds"])),
                         "reference_runs_per_decision": float(np.mean(runs))}
        row["speedup"] = ratio(figures, "settled first", "deferred")
        out["depths"][depth] = row
        d, e = row["deferred"], row["settled first"]
        print(f"depth {depth}: deferred {d['seconds_per_decision']:.2f} s and {d['reference_runs_per_decision']:.1f} "
              f"reference runs a decision, settled first {e['seconds_per_decision']:.2f} s and "
              f"{e['reference_runs_per_decision']:.1f}: {row['speedup']:.2f}x; the same decision in "
              f"{row['same_decisions']} of {len(cases)}", flush=True)
    out["wall_seconds"] = time.perf_counter() - started
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.out, out)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
