"""The card's command against the code of another revision, side by side:
``python -m overhang_framework.bench.headline --before REV``.

Runs ``python -m overhang_framework predictor=hybrid planner=lookahead planner.depth=3`` (or
``--command``'s overrides) on ``paper20``, once with this checkout and once with the code of git revision
``REV`` (checked out into a temporary worktree and imported ahead of this one, in the same virtual
environment), ``--rounds`` times, alternating which goes first (:mod:`overhang_framework.bench.sidebyside`).
Each run is the literal command in its own process, every task in it as a user runs it (``--per-task``:
each task in a process of its own, alternating task by task), so what is timed is what a user waits for:
the decision times its ``episodes.jsonl`` records. Prints, for each side, the median, mean and maximum
decision time over every decision and over the decisions with three or more blocks left, and how many
placements the two sides made alike; the last line is one JSON object (``--out FILE`` writes it too).

    python -m overhang_framework.bench.headline --before 3fff5aa
    python -m overhang_framework.bench.headline --before 3fff5aa --rounds 2
    python -m overhang_framework.bench.headline --before 3fff5aa --limit 5 --per-task --command predictor=cnn planner=lookahead planner.depth=2
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np

from overhang_framework.bench.sidebyside import side_by_side

ROOT = Path(__file__).resolve().parents[2]
CARD = ["predictor=hybrid", "planner=lookahead", "planner.depth=3"]


@contextlib.contextmanager
def worktree(rev: str) -> Iterator[Path]:
    """A temporary detached checkout of ``rev`` beside this repository, removed afterwards."""
    where = Path(tempfile.mkdtemp(prefix="overhang-before-"))
    done = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(where / "tree"), rev],
                          capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"error: cannot check out revision {rev!r}: {done.stderr.strip().splitlines()[-1]}")
    try:
        yield where / "tree"
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(where / "tree")],
                       capture_output=True)


def run_tasks(code: Optional[Path], overrides: Sequence[str], tasks: Sequence[str], out: Path) -> list[list[dict]]:
    """The steps of each episode of the command on ``tasks`` (one process), run by the code at ``code``
    (None: this checkout), in the order of the tasks."""
    env = dict(os.environ, OVERHANG_PROGRESS_SECONDS="0")
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(code), str(code / "plugins"), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "overhang_framework", *overrides, f"tasks.only=[{','.join(tasks)}]",
           f"hydra.run.dir={out}", "overwrite=true", "progress=false"]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(code or ROOT))
    if done.returncode:
        raise SystemExit(f"error: {' '.join(cmd)} failed: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
    episodes = {e["task_id"]: e for e in (json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()
                                          if line.strip())}
    return [episodes[t]["steps"] for t in tasks]


def summary(steps_by_task: Sequence[list[dict]], remaining_from: Sequence[int]) -> dict:
    times = [s["decision_time"] for steps in steps_by_task for s in steps]
    deep = [s["decision_time"] for steps, n in zip(steps_by_task, remaining_from) for k, s in enumerate(steps)
            if n - k >= 3]
    return {"decisions": len(times), "median_seconds": float(np.median(times)), "mean_seconds": float(np.mean(times)),
            "max_seconds": float(np.max(times)), "deep_decisions": len(deep),
            "deep_median_seconds": float(np.median(deep)) if deep else float("nan")}


def main(argv: Optional[Sequence[str]] = None) -> dict:
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.headline",
                                 description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--before", required=True, help="the git revision to compare with (e.g. a commit or tag)")
    ap.add_argument("--limit", type=int, default=None, help="the first N tasks of paper20 only")
    ap.add_argument("--command", nargs="*", default=CARD, help="the command's overrides (default: the card's)")
    ap.add_argument("--rounds", type=int, default=1, help="whole runs of each version (default 1)")
    ap.add_argument("--per-task", action="store_true", help="each task in a process of its own")
    ap.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error(f"--rounds takes a whole number >= 1, got {args.rounds}")
    tasks = tasks_from_config(compose_config(["tasks=paper20"]).tasks)[:args.limit]
    started = time.perf_counter()
    with worktree(args.before) as before, tempfile.TemporaryDirectory() as tmp:
        runs = {"before": before, "now": None}
        steps: dict = {n: [] for n in runs}
        ids = [t.id for t in tasks]
        cases = [[t] for t in ids] if args.per_task else [ids] * args.rounds
        order = [list(c) for c in cases]

        def version(name):
            def play(case):  # the placements are compared; the steps, with their times, are kept
                played = run_tasks(runs[name], args.command, case, Path(tmp) / name / f"{len(steps[name])}")
                steps[name].extend(played)
                return [[(s["x"], s["layer"]) for s in ep] for ep in played]
            return play

        figures = side_by_side(order, {n: version(n) for n in runs}, label=lambda c: ",".join(c) if len(c) < 4
                               else f"{len(c)} tasks", quiet=False)
    remaining = [len(t.sequence) - 1 for t in tasks] * (1 if args.per_task else args.rounds)
    out = {"command": list(args.command), "before": args.before, "tasks": len(tasks), "rounds": args.rounds,
           "per_task": args.per_task, "wall_seconds": 0.0, "runs_alike": figures["same"]}
    placed = steps
    alike = sum(a == b for ra, rb in zip(figures["versions"]["before"]["results"], figures["versions"]["now"]["results"])
                for sa, sb in zip(ra, rb) for a, b in zip(sa, sb))
    for name in runs:
        out[name] = summary(placed[name], remaining)
        out[name]["reward_steps"] = sum(len(s) for s in placed[name])
        v = out[name]
        print(f"{name:>6}: median decision {v['median_seconds']:.3f} s, mean {v['mean_seconds']:.3f} s, "
              f"max {v['max_seconds']:.2f} s over {v['decisions']} decisions; with 3+ blocks left median "
              f"{v['deep_median_seconds']:.3f} s", flush=True)
    out["placements_alike"] = alike
    out["median_ratio"] = out["before"]["median_seconds"] / out["now"]["median_seconds"]
    out["max_ratio"] = out["before"]["max_seconds"] / out["now"]["max_seconds"]
    print(f"{alike} of {out['now']['reward_steps']} placements alike; the median decision "
          f"{out['median_ratio']:.2f}x and the longest {out['max_ratio']:.2f}x faster now", flush=True)
    out["wall_seconds"] = time.perf_counter() - started
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.out, out)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
