"""Simulated participants on the benchmark's axes: ``python -m overhang_framework.benchmark.people LOG``.

Reads a behaviour log of simulated participants who did ``paper20`` (``python -m
overhang_framework.participants``), and keeps per condition their score (reward / optimum of the
trial's task under the default physics, averaged over trials per task, then over tasks), mean raw
reward, share of trials that stood, and the predictor calls their decisions were allowed, in
``overhang_framework/data/benchmark_people.json``, where the benchmark's figures find them::

    python -m overhang_framework.participants cohort=paper hydra.run.dir=runs/sim-paper jobs=2
    python -m overhang_framework.benchmark.people runs/sim-paper/log.jsonl
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

import numpy as np

from overhang_framework.benchmark.figures import SIMULATED


def rows_of(log_path: str, optima_path: Optional[str] = None) -> list[dict]:
    """Per condition: score, interval, mean reward, share stood, participants and trials."""
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.behaviour.table1 import trial_outcomes
    from overhang_framework.benchmark.score import bootstrap_interval
    from overhang_framework.benchmark.splits import task_id
    from overhang_framework.optimum import load_optima, optimum_key
    from overhang_framework.plugins import Registry
    from overhang_framework.interfaces import Task

    from overhang_framework.behaviour.analysis import with_groups

    df = with_groups(read_log(log_path))
    world = Registry().create("world", {"name": "overhang"})
    optima = load_optima(optima_path)
    sequences = df.drop_duplicates(["participant", "trial"]).set_index(["participant", "trial"])["sequence"]
    trials = trial_outcomes(df)
    rows = []
    for group, t in sorted(trials.groupby("group"), key=lambda kv: str(kv[0])):
        by_task: dict = {}
        for p, trial, reward in zip(t["participant"], t["trial"], t["reward"]):
            seq = tuple(float(w) for w in sequences[(p, trial)])
            row = optima.get(optimum_key(Task("x", seq), world))
            if row is not None:
                by_task.setdefault(task_id(seq), []).append(float(reward) / float(row["optimum"]))
        values = [float(np.mean(v)) for _, v in sorted(by_task.items())]
        low, high = bootstrap_interval(values)
        rows.append({"condition": str(group), "score": float(np.mean(values)), "ci_low": low, "ci_high": high,
                     "reward": float(t["reward"].mean()), "stood": float(t["stood"].mean()),
                     "participants": int(t["participant"].nunique()), "trials": int(len(t)), "tasks": len(values)})
    return rows


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.results import atomic_write_json

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.benchmark.people", description=__doc__.split("\n\n")[0])
    ap.add_argument("log", help="a behaviour log of simulated participants on paper20")
    ap.add_argument("--out", default=str(SIMULATED), help=f"where to keep the rows (default {SIMULATED})")
    ap.add_argument("--command", default="", help="the command that made the log, kept with the rows")
    args = ap.parse_args(argv)
    try:
        rows = rows_of(args.log)
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    atomic_write_json(args.out, {"log_command": args.command, "rows": rows,
                                 "note": "simulated participants on paper20; score = reward / optimum (default physics)"})
    for r in rows:
        print(f"{r['condition']}: score {r['score']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}], reward "
              f"{r['reward']:.3f}, stood {100 * r['stood']:.0f}% ({r['participants']} participants, {r['trials']} trials)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
