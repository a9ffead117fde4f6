"""Lookahead with the world's verdicts, deferring the reference against settling first, side by side:
``python -m overhang_framework.bench.lookahead_defer``.

On decision states of the benchmark's ``test`` split (``--tasks`` tasks spread over the split, each
after every count of ``--placed`` placements of the myopic planner under the static physics), one lookahead decision with
the veridical predictor under the default physics (the full-window reference where the static stages
are unsure), ``planner.defer=true`` (the default) beside ``false`` (every unsure child settled before
its subtree), each from an empty verdict cache (a new world, no verdict file), alternating which goes
first (:mod:`overhang_framework.bench.sidebyside`). Prints each version's seconds and reference runs per
decision at each depth and whether every decision was the same (the action, and the number of tied
best actions the random tie-break saw); ``--seed`` seeds the tie-breaks. The last line is one JSON object
(``--out FILE`` writes it too).

    python -m overhang_framework.bench.lookahead_defer
    python -m overhang_framework.bench.lookahead_defer --tasks 20 --placed 1,2 --depths 2,3
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Optional, Sequence

import numpy as np

from overhang_framework.bench.sidebyside import ratio, side_by_side


def states(n_tasks: int, placed: Sequence[int], seed: int = 0):
    """Decision states: ``n_tasks`` tasks of ``test`` spread over the split (its ids are sorted by widths),
    after each count of ``placed`` placements (the myopic planner's, ties broken by ``seed``)."""
    from overhang_framework.benchmark.splits import split_ids, task
    from overhang_framework.interfaces import Budget
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    planner = registry.create("planner", {"name": "myopic"}, world=world)
    out = []
    ids = split_ids("test")
    for tid in ids[::max(1, len(ids) // n_tasks)][:n_tasks]:
        state = world.initial_state(task(tid))
        for k in range(max(placed) + 1):
            if k in placed:
                out.append((tid, k, state))
            if state.done:
                break
            rng = np.random.default_rng([seed, k])
            state = world.step(state, planner.plan(state, predictor, value, Budget(), rng).action)
    return out


def decide(state, depth: int, defer: bool, seed: int, runs: list) -> tuple:
    """One decision from an empty verdict cache: the action, its choice probability (one over the tied best
    actions) and rank, compared across the versions; its reference runs are appended to ``runs``."""
    from overhang_framework.interfaces import Budget
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang"})
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    planner = registry.create("planner", {"name": "lookahead", "depth": depth, "defer": defer}, world=world)
    d = planner.plan(state, predictor, value, Budget(), np.random.default_rng(seed))
    runs.append(int(((world.stats().get("cache") or {}).get("backend") or {}).get("reference", 0)))
    close = getattr(world.backend, "close", None)
    if close is not None:
        close()
    return (round(d.action.x, 6), d.action.layer), d.choice_probability, d.choice_rank


def main(argv: Optional[Sequence[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.lookahead_defer",
                                 description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tasks", type=int, default=8, help="N tasks of test, spread over the split (default 8)")
    ap.add_argument("--placed", default="0,1", help="placements before each decision state (default 0,1)")
    ap.add_argument("--depths", default="2,3", help="lookahead depths (default 2,3)")
    ap.add_argument("--seed", type=int, default=0, help="the decisions' and the myopic placements' seed (default 0)")
    ap.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = ap.parse_args(argv)
    try:
        placed = sorted({int(w) for w in args.placed.split(",")})
        depths = [int(w) for w in args.depths.split(",")]
    except ValueError:
        ap.error("--placed and --depths take comma-separated whole numbers")
    if args.tasks < 1 or min(placed) < 0 or min(depths) < 1:
        ap.error("--tasks and --depths take numbers >= 1, --placed numbers >= 0")
    cases = states(args.tasks, placed, args.seed)
    started = time.perf_counter()
    out = {"tasks": args.tasks, "placed": placed, "seed": args.seed, "states": len(cases), "depths": {}}
    for depth in depths:
        print(f"depth {depth}: {len(cases)} states, each from an empty verdict cache", flush=True)
        runs = {"deferred": [], "settled first": []}
        figures = side_by_side(cases, {name: (lambda c, d=depth, f=(name == "deferred"), r=runs[name]:
                                              decide(c[2], d, f, args.seed, r)) for name in runs},
                               label=lambda c: f"{c[0]} after {c[1]}", quiet=False)
        row = {"same_decisions": figures["same"]}
        for name in runs:
            v = figures["versions"][name]
            row[name] = {"seconds_per_decision": v["total"] / len(cases),
                         "median_seconds": float(np.median(v["seconds"])),
                         "reference_runs_per_decision": float(np.mean(runs[name]))}
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
