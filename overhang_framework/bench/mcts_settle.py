"""MCTS with the veridical predictor, every answer settled or only the needed ones:
``python -m overhang_framework.bench.mcts_settle [--tasks 4] [--iterations 200]``.

The veridical predictor's answers are the world's verdicts. Its static stages judge most towers at once; the
others need the full-window reference run. MCTS with ``lazy: false`` settles every child of a state when the
state is expanded; with ``lazy: true`` (the default) a node settles a child only when the search needs its
exact answer (:mod:`plugins.overhang_builtins.mcts`). This plays whole benchmark episodes of ``test`` tasks
(seed 0) both ways, side by side, the order alternating task by task, each with a world of its own (no
verdict file, an empty cache). For each task it prints the seconds and the reference runs of each way, and
whether the two episodes' records are the same apart from their seconds. Measured on whatever else the
machine is doing. The last line is one JSON object with the figures; ``--out FILE`` also writes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

WAYS = {"eager": False, "lazy": True}


def _strip(record: dict) -> dict:
    """A record without its timings."""
    out = {k: v for k, v in record.items() if k != "seconds"}
    out["steps"] = [{k: v for k, v in step.items() if k != "seconds"} for step in record["steps"]]
    return out


def play_once(task, iterations: int, lazy: bool) -> tuple[dict, int]:
    """One seed-0 episode of ``task``: its record and the world's reference runs."""
    from overhang_framework.benchmark.agents import play
    from overhang_framework.benchmark.run import CONFIG_NAME, build_agent
    from overhang_framework.config import compose_config
    from omegaconf import OmegaConf

    cfg = compose_config(["planner=mcts", "predictor=veridical", "verdicts=null", f"planner.iterations={iterations}",
                          f"+planner.lazy={str(lazy).lower()}"], config_name=CONFIG_NAME)
    world, agent = build_agent(OmegaConf.to_container(cfg, resolve=True), Path("."))
    record = play(agent, world, task, 0)
    return record, int(world.stats()["cache"]["backend"]["reference"])  # the tiered physics' stage counts


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.mcts_settle",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=4, help="test tasks, spread over the split (default 4)")
    ap.add_argument("--iterations", type=int, default=200, help="MCTS simulations a decision (default 200)")
    ap.add_argument("--out", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    if args.tasks < 1 or args.iterations < 1:
        print("error: --tasks and --iterations must be whole numbers >= 1", file=sys.stderr)
        return 2
    from overhang_framework.benchmark import splits

    ids = splits.split_ids("test", None)
    step = max(1, len(ids) // args.tasks)
    chosen = ids[::step][:args.tasks]
    rows = []
    print(f"{'task':10} {'eager s':>9} {'lazy s':>9} {'eager ref':>10} {'lazy ref':>9} {'same':>5}", flush=True)
    for k, tid in enumerate(chosen):
        task = splits.task(tid)
        got = {}
        for way in (list(WAYS) if k % 2 == 0 else list(WAYS)[::-1]):
            record, refs = play_once(task, args.iterations, WAYS[way])
            got[way] = (record, refs)
        same = _strip(got["eager"][0]) == _strip(got["lazy"][0])
        row = {"task": tid, "same": same, "reward": got["lazy"][0]["reward"],
               **{f"{w}_seconds": got[w][0]["seconds"] for w in WAYS},
               **{f"{w}_reference": got[w][1] for w in WAYS}}
        rows.append(row)
        print(f"{tid:10} {row['eager_seconds']:9.1f} {row['lazy_seconds']:9.1f} {row['eager_reference']:10d} "
              f"{row['lazy_reference']:9d} {'yes' if same else 'NO':>5}", flush=True)
    total = {w: sum(r[f"{w}_seconds"] for r in rows) for w in WAYS}
    refs = {w: sum(r[f"{w}_reference"] for r in rows) for w in WAYS}
    summary = {"tasks": len(rows), "iterations": args.iterations, "identical": all(r["same"] for r in rows),
               "seconds": total, "reference_runs": refs,
               "speedup": total["eager"] / total["lazy"] if total["lazy"] > 0 else None,
               "reference_ratio": refs["eager"] / refs["lazy"] if refs["lazy"] > 0 else None, "rows": rows}
    print(f"total: eager {total['eager']:.1f} s, lazy {total['lazy']:.1f} s ({summary['speedup']:.2f}x); "
          f"reference runs {refs['eager']} against {refs['lazy']}; episodes identical: "
          f"{'yes' if summary['identical'] else 'no'}")
    print(json.dumps(summary))
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(Path(args.out), summary)
    return 0 if summary["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
