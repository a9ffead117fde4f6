"""Search against the reference physics: the lazy search beside the exhaustive one, over the same states.

Under the default (tiered) physics a verdict near a tipping point costs a full-window PyBullet run.
The exhaustive search asks for the verdict of every child of every state it expands; the lazy search
(:class:`~overhang_framework.search.Expansion`) counts an unsure child as standing in its bounds and
runs the reference only for the children that could still change its result. Both must choose the
same action with the same value; this benchmark checks that on every state and prints, side by side
in one run, the time, the decisions per second and the reference runs of each:

* depth-3 lookahead with the veridical predictor on mid-episode paper20 states (two blocks placed by
  the myopic planner; target: at most 2 s median for the lazy search);
* with ``--myopic``, the myopic decision of the same states.

Each decision starts from a cold physics cache (a fresh world). The last line is one JSON object.

    python -m overhang_framework.bench.reference_search --states 8
    python -m overhang_framework.bench.reference_search --states 8 world.workers=2
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

import numpy as np


def decide(overrides: Sequence[str], state, depth: int, lazy: bool) -> dict:
    """One decision from a cold cache: the best root actions, their score, seconds and reference runs."""
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.interfaces import Budget
    from overhang_framework.search import Expander, root_scores, ties

    cfg = compose_config([*overrides, "predictor=veridical", "planner=lookahead", f"planner.depth={depth}"])
    models = build_models(cfg)
    world = models["world"]
    expander = Expander(world, models["predictor"], Budget(), seed=0, lazy=lazy)
    started = time.perf_counter()
    scores = root_scores(expander, models["value"], state, depth, exact_all=False, prefetch=True)
    seconds = time.perf_counter() - started
    stages = (world.stats().get("cache") or {}).get("backend") or {}
    close = getattr(world.backend, "close", None)
    if close is not None:
        close()
    return {"best": sorted(ties(scores).tolist()), "value": round(float(scores.max()), 9), "seconds": seconds,
            "reference_runs": int(stages.get("reference", 0)), "states_expanded": expander.stats.nodes_expanded}


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.bench.reference_search",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="config overrides (e.g. world.workers=2)")
    parser.add_argument("--states", type=int, default=8, help="states, one per paper20 task (default 8)")
    parser.add_argument("--depth", type=int, default=3, help="lookahead depth (default 3)")
    parser.add_argument("--lazy-only", action="store_true", help="time the lazy search alone")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.states < 1 or args.depth < 1:
        print("error: --states and --depth must be whole numbers >= 1", file=sys.stderr)
        return 2
    from overhang_framework.bench.planners import mid_episode_states
    from overhang_framework.preflight import overrides_problem
    from overhang_framework.progress import progress_bar

    problem = overrides_problem(args.overrides)
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    states = mid_episode_states(args.overrides, args.states)
    kinds = ["lazy"] if args.lazy_only else ["lazy", "exhaustive"]
    rows = []
    bar = progress_bar(total=len(states) * len(kinds), desc=f"D={args.depth} decisions", unit="decision",
                       disable=args.quiet, file=sys.stderr)
    for i, state in enumerate(states):
        row = {"state": i}
        for kind in kinds:
            row[kind] = decide(args.overrides, state, args.depth, lazy=kind == "lazy")
            bar.update(1)
        if "exhaustive" in row and (row["lazy"]["best"], row["lazy"]["value"]) != \
                (row["exhaustive"]["best"], row["exhaustive"]["value"]):
            bar.close()
            print(f"error: state {i}: the lazy search chose {row['lazy']['best']} ({row['lazy']['value']}), the "
                  f"exhaustive one {row['exhaustive']['best']} ({row['exhaustive']['value']})", file=sys.stderr)
            return 1
        rows.append(row)
    bar.close()
    print(f"{'state':>5}  " + "  ".join(f"{k + ' s':>14} {k + ' runs':>16}" for k in kinds) + "  same choice")
    for row in rows:
        cells = "  ".join(f"{row[k]['seconds']:14.2f} {row[k]['reference_runs']:16d}" for k in kinds)
        print(f"{row['state']:5d}  {cells}  {'yes' if len(kinds) > 1 else '-'}")
    summary = {}
    for k in kinds:
        s = np.array([row[k]["seconds"] for row in rows])
        runs = np.array([row[k]["reference_runs"] for row in rows])
        summary[k] = {"median_s": float(np.median(s)), "q25_s": float(np.quantile(s, 0.25)),
                      "q75_s": float(np.quantile(s, 0.75)), "decisions_per_s": float(len(s) / s.sum()),
                      "mean_reference_runs": float(runs.mean())}
        print(f"{k:>10}: median {summary[k]['median_s']:.2f} s (quartiles {summary[k]['q25_s']:.2f}-"
              f"{summary[k]['q75_s']:.2f}), {summary[k]['decisions_per_s']:.3f} decisions/s, "
              f"{summary[k]['mean_reference_runs']:.0f} reference runs per decision")
    if len(kinds) > 1:
        print(f"speed-up (decisions/s): {summary['lazy']['decisions_per_s'] / summary['exhaustive']['decisions_per_s']:.1f}x; "
              f"the same choice and value on all {len(rows)} states")
    print(json.dumps({"overrides": list(args.overrides), "depth": args.depth, "summary": summary, "states": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
