"""Planner speed: one lookahead decision on mid-episode states, with the figures that explain it.

For each task of the task set, the first two blocks are placed by the myopic
planner (three blocks in the scene, three left to place), and one decision is
timed from a cold physics cache:

* lookahead depth 3 with the veridical predictor (target: at most 1 s median);
* lookahead depth 2 with the IPE, K = 50 (target: at most 2 s median).

For each it prints the median and quartiles of the decision time, the states
expanded per second, the share of the exhaustive search's candidate
evaluations that pruning skipped (the unpruned search is run afterwards to
count them), and the physics cache's hit rate. The last line is one JSON object.

    python -m overhang_framework.bench.planners
    python -m overhang_framework.bench.planners --states 5 world.physics=static
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

import numpy as np


def mid_episode_states(overrides: Sequence[str], n: int, placed: int = 2) -> list:
    """States with ``placed`` blocks put down by the myopic planner, one per task (first ``n`` tasks)."""
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.interfaces import Budget
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_config([*overrides, "planner=myopic", "predictor=veridical"])
    models = build_models(cfg)
    world = models["world"]
    states = []
    for i, task in enumerate(tasks_from_config(cfg.tasks)[:n]):
        state = world.initial_state(task)
        for _ in range(placed):
            d = models["planner"].plan(state, models["predictor"], models["value"], Budget(),
                                       np.random.default_rng(i))
            state = world.step(state, d.action)
        states.append(state)
    return states


def decisions(overrides: Sequence[str], states: list, predictor: str, depth: int, quiet: bool) -> dict:
    """Time one cold-cache decision per state; count what pruning saved."""
    from overhang_framework.progress import progress_bar

    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.interfaces import Budget

    seconds, nodes, calls, pruned_work, full_work, hits, lookups = [], [], [], [], [], 0, 0
    for i, state in enumerate(progress_bar(states, desc=f"{predictor} D={depth}", disable=quiet, file=sys.stderr)):
        cfg = compose_config([*overrides, f"predictor={predictor}", "planner=lookahead", f"planner.depth={depth}"])
        models = build_models(cfg)  # a fresh world: a cold physics cache
        world, planner, pred, value = models["world"], models["planner"], models["predictor"], models["value"]
        before = (world.stats().get("cache") or {})
        started = time.perf_counter()
        d = planner.plan(state, pred, value, Budget(), np.random.default_rng(i))
        seconds.append(time.perf_counter() - started)
        after = (world.stats().get("cache") or {})
        hits += after.get("hits", 0) - before.get("hits", 0)
        lookups += (after.get("hits", 0) + after.get("misses", 0)) - (before.get("hits", 0) + before.get("misses", 0))
        nodes.append(d.spend.nodes_expanded)
        calls.append(d.spend.predictor_calls)
        pruned_work.append(d.spend.actions_scored)
        planner.prune = False
        full = planner.plan(state, pred, value, Budget(), np.random.default_rng(i))
        full_work.append(full.spend.actions_scored)
        if full.action != d.action:
            raise AssertionError(f"pruning changed the choice on state {i}")
    s = np.asarray(seconds)
    return {
        "predictor": predictor, "depth": depth, "decisions": len(s),
        "median_s": float(np.median(s)), "q25_s": float(np.quantile(s, 0.25)), "q75_s": float(np.quantile(s, 0.75)),
        "max_s": float(s.max()), "nodes_per_s": float(np.sum(nodes) / np.sum(s)),
        "mean_predictor_calls": float(np.mean(calls)),
        "pruned_share": float(1 - np.sum(pruned_work) / np.sum(full_work)),
        "cache_hit_rate": hits / lookups if lookups else None,
    }


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.bench.planners",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="config overrides (e.g. world.physics=static)")
    parser.add_argument("--states", type=int, default=10, help="decisions timed per setting (default 10)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.states < 1:
        print(f"error: --states must be a whole number >= 1, got {args.states}", file=sys.stderr)
        return 2
    from overhang_framework.preflight import overrides_problem

    problem = overrides_problem(args.overrides)
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        import torch  # noqa: F401  (when present, one thread, so figures do not depend on the other core)

        torch.set_num_threads(1)
    except ImportError:
        pass
    states = mid_episode_states(args.overrides, args.states)
    results = [decisions(args.overrides, states, "veridical", 3, args.quiet),
               decisions(args.overrides, states, "ipe", 2, args.quiet)]
    for r in results:
        hit = "n/a" if r["cache_hit_rate"] is None else f"{r['cache_hit_rate']:.2f}"
        print(f"{r['predictor']:>10} D={r['depth']}: median {r['median_s']:.3f} s "
              f"(quartiles {r['q25_s']:.3f}-{r['q75_s']:.3f}, max {r['max_s']:.3f}), "
              f"{r['nodes_per_s']:.0f} states/s, {r['mean_predictor_calls']:.0f} predictor calls, "
              f"pruning skipped {100 * r['pruned_share']:.0f}% of candidate evaluations, cache hit rate {hit}")
    print(json.dumps({"overrides": list(args.overrides), "results": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
