"""Lazy answers in deep searches: ``python -m overhang_framework.bench.lazy [--depths 2,3] [--states 4]``.

A lookahead planner with a softmax choice needs every root action's exact score. This times that search
(:func:`~overhang_framework.search.root_scores`, as ``planner=lookahead planner.choice=softmax`` runs it) on
mid-episode states, three ways, side by side on the same states in one run, the order rotated state by
state:

* ``eager``: the predictor scores every child of a state when the state is expanded, and the children of
  a node one level above the leaves are expanded together (the planner's ``prefetch``, which it keeps
  under a call budget);
* ``eager, no prefetch``: the same, each state expanded when the search reaches it (the planner's way for
  a network from depth 3 without a budget);
* ``lazy``: the predictor's ``lazy: true``. An inner node's children are scored together when it is
  expanded, the leaves best bound first, a ``settle_batch`` at a time, and only while they can still
  change the result.

For each family and depth it prints the median seconds of a decision, the towers the predictor scored
(the CNN's towers through the network; a hybrid's also counts its IPE's candidates; the IPE alone, 0), the speed-up of ``lazy`` over
``eager``, and the largest difference between the scores (the three are the same numbers). The
predictors' caches are emptied before every timed search. Measured on whatever else the machine is doing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

#: family -> the predictor config, and how to make it lazy
FAMILIES = {"cnn": ({"name": "cnn"}, {"lazy": True}),
            "hybrid": ({"name": "hybrid"}, {"early_params": {"lazy": True}, "late_params": {"lazy": True}}),
            "ipe": ({"name": "ipe", "K": 50}, {"lazy": True})}
WAYS = ("eager", "eager, no prefetch", "lazy")


def _towers(predictor) -> int:
    stats = getattr(predictor, "stats", lambda: {})()
    if "towers" in stats:  # the CNN: towers asked about (cache hits included)
        return int(stats["towers"] - stats.get("cache_hits", 0))
    if "late_stats" in stats:  # the hybrid: the network's towers and the IPE's candidates
        late = stats["late_stats"] or {}
        return int(late.get("towers", 0) - late.get("cache_hits", 0)) + int(stats.get("early_actions", 0))
    return 0  # the IPE does not count its candidates


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.lazy", description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=4, help="mid-episode states, one per task (default 4)")
    ap.add_argument("--placed", type=int, default=1, help="blocks placed before the timed decision (default 1)")
    ap.add_argument("--depths", default="2,3", help="search depths (default 2,3)")
    ap.add_argument("--families", default="cnn,hybrid", help="predictor families: cnn, hybrid, ipe (default cnn,hybrid)")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        print(f"error: unknown family {unknown[0]!r}; allowed: {', '.join(FAMILIES)}", file=sys.stderr)
        return 2

    from overhang_framework.bench.planners import mid_episode_states
    from overhang_framework.interfaces import Budget
    from overhang_framework.plugins import Registry
    from overhang_framework.search import Expander, root_scores

    overrides = ["world.physics=static"]
    states = mid_episode_states(overrides, args.states, placed=args.placed)
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    value = registry.create("value", {"name": "overhang"}, world=world)
    figures: dict = {"states": len(states), "placed": args.placed, "rows": []}
    print(f"one softmax lookahead decision on {len(states)} mid-episode states ({args.placed} block(s) placed), "
          f"static physics; median seconds and towers scored per decision:", flush=True)
    print(f"  {'model':<12}" + "".join(f"{w:>26}" for w in WAYS) + f"{'lazy faster':>13}{'max diff':>10}", flush=True)
    for depth in [int(d) for d in args.depths.split(",") if d]:
        for family in families:
            base, lazy_params = FAMILIES[family]
            made = {"eager": registry.create("predictor", dict(base), world=world),
                    "lazy": registry.create("predictor", _merged(base, lazy_params), world=world)}
            made["eager, no prefetch"] = made["eager"]
            seconds = {w: [] for w in WAYS}
            towers = {w: [] for w in WAYS}
            diff = 0.0
            for n, state in enumerate(states):
                scores = {}
                for w in WAYS[n % 3:] + WAYS[:n % 3]:
                    predictor = made[w]
                    getattr(predictor, "clear_cache", lambda: None)()
                    before = _towers(predictor)
                    expander = Expander(world, predictor, Budget(), seed=n)
                    t0 = time.perf_counter()
                    scores[w] = root_scores(expander, value, state, depth, True, prefetch=w == "eager")
                    seconds[w].append(time.perf_counter() - t0)
                    towers[w].append(_towers(predictor) - before)
                diff = max(diff, *(float(np.max(np.abs(scores[w] - scores["eager"]), initial=0.0)) for w in WAYS))
            med = {w: float(np.median(seconds[w])) for w in WAYS}
            row = {"model": f"{family}/D{depth}", "median_seconds": med,
                   "towers": {w: float(np.mean(towers[w])) for w in WAYS},
                   "lazy_speedup": med["eager"] / med["lazy"], "max_score_difference": diff}
            figures["rows"].append(row)
            print(f"  {row['model']:<12}" + "".join(f"{med[w]:>10.2f} s {row['towers'][w]:>9.0f} tw" for w in WAYS)
                  + f"{row['lazy_speedup']:>12.2f}x{diff:>10.1e}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


def _merged(base: dict, extra: dict) -> dict:
    out = dict(base)
    for key, val in extra.items():
        out[key] = {**out.get(key, {}), **val} if isinstance(val, dict) else val
    return out


if __name__ == "__main__":
    sys.exit(main())
