"""The paper's Table 2 from a sweep: terminal reward per model beside the paper's values.

``experiment=table2`` makes :class:`Table2Callback` its sweep callback, so the
table is printed and written to ``table2.md`` in the sweep directory when
the sweep ends. It can be made again from the files alone, also for a partial
sweep:

    python -m overhang_framework.report.table2 multirun/table2-unconstrained/2026-11-23/10-00-00

Each model's terminal reward is the mean over all its episodes; the ± is the
standard error of the mean across tasks (of each task's mean over its runs),
since the tasks, not the runs of one task, are the independent units. Reward /
optimum divides every episode's reward by its task's optimum
(``overhang_framework/data/optima.json``, which holds the optima for the
static physics; see ``docs/table2.md``).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from overhang_framework.report.build import Job, load_jobs, mean_pm, optimum_of
from overhang_framework.report.callback import SweepResults
from overhang_framework.results import atomic_write_text, mean_sem, median

#: The paper's Table 2 (mean ± SEM of terminal reward over its 20 tasks), as printed there.
PAPER = {
    "Human (w/ time limit)": "0.913 ± 0.03",
    "Human (w/o time limit)": "0.979 ± 0.03",
    "Myopic": "0.52 ± 0.12",
    "Lookahead (D=2)": "0.912 ± 0.10",
    "Lookahead (D=3)": "1.180 ± 0.24",
}
#: The order of the model rows, after the people.
MODEL_ORDER = ("Myopic", "Lookahead (D=2)", "Lookahead (D=3)")


def model_name(config: dict) -> str:
    """The paper's name for a job's planner: ``Myopic``, ``Lookahead (D=2)``, ...; other planners by name."""
    planner = config.get("planner", {})
    name = str(planner.get("name", "?"))
    if name == "myopic":
        return "Myopic"
    if name == "lookahead":
        return f"Lookahead (D={planner.get('depth', '?')})"
    return name


def task_sem(episodes: list[dict], values: Sequence[float]) -> tuple[float, float, int]:
    """Mean of ``values`` over all episodes, the SEM across tasks' means, and the number of tasks."""
    by_task: dict[str, list[float]] = {}
    for episode, v in zip(episodes, values):
        by_task.setdefault(episode["task_id"], []).append(float(v))
    if not by_task:
        return math.nan, math.nan, 0
    _, sem = mean_sem(np.mean(v) for v in by_task.values())
    return float(np.mean(values)), sem, len(by_task)


def rows_of(jobs: list[Job], optima: dict) -> list[dict]:
    """One row per job: model, condition, predictor, episodes, reward and reward / optimum."""
    rows = []
    for job in jobs:
        eps = job.episodes
        reward, sem, tasks = task_sem(eps, [e["reward"] for e in eps])
        own = [optimum_of(job, e, optima) for e in eps]
        best = [b or static_optimum(job, e, optima) for b, e in zip(own, eps)]
        if eps and all(best):
            ratio, ratio_sem, _ = task_sem(eps, [e["reward"] / b for e, b in zip(eps, best)])
        else:
            ratio, ratio_sem = math.nan, math.nan
        repeats = job.config.get("repeats")
        rows.append({"job": job.name, "model": model_name(job.config), "status": job.status,
                     "condition": job.config.get("condition", {}).get("name", "?"),
                     "predictor": job.config.get("predictor", {}).get("name", "?"),
                     "episodes": len(eps), "expected": job.expected, "tasks": tasks, "repeats": repeats,
                     "reward": reward, "sem": sem, "ratio": ratio, "ratio_sem": ratio_sem,
                     "optimum_of": "own" if eps and all(own) else "static",
                     "decision_time": median([s["decision_time"] for e in eps for s in e["steps"]]),
                     **_depths(eps, job.config)})
    order = {name: i for i, name in enumerate(MODEL_ORDER)}
    rows.sort(key=lambda r: (r["condition"], order.get(r["model"], len(order)), r["model"], r["job"]))
    return rows


def static_optimum(job: Job, episode: dict, optima: dict) -> Optional[float]:
    """The task's optimum under the static physics at the job's resolution (the shipped optima), when
    the job's own physics has none: the tiered world differs from it only near a tipping point."""
    resolution = job.config.get("world", {}).get("resolution")
    sequence = [round(w, 6) for w in episode["sequence"]]
    for row in optima.values():
        if row.get("physics") == "static" and row.get("resolution") == resolution \
                and [round(w, 6) for w in row.get("sequence", [])] == sequence:
            return float(row["optimum"])
    return None


def _depths(episodes: list[dict], config: dict) -> dict:
    """Over the decisions that could search the planner's full depth (enough blocks left): the mean depth
    the search completed and the share whose budget ran out."""
    planner = config.get("planner", {})
    full = int(planner.get("depth", 1)) if planner.get("name") == "lookahead" else 1
    depths, ran_out = [], []
    for e in episodes:
        n = len(e["sequence"]) - 1
        for i, step in enumerate(e["steps"]):
            if n - i >= full:
                spend = step.get("spend", {})
                depths.append(float(spend.get("depth_completed", full)))
                ran_out.append(float(bool(spend.get("budget_exhausted"))))
    return {"depth": float(np.mean(depths)) if depths else math.nan,
            "ran_out": float(np.mean(ran_out)) if ran_out else math.nan}


def _two(value: float) -> str:
    return "-" if value is None or math.isnan(value) else f"{value:.2f}"


def render(rows: list[dict], root: Path) -> str:
    """The Markdown table: the paper's rows and ours side by side."""
    lines = [f"# Table 2: terminal reward across the tasks ({root})", "",
             "| model | paper | ours | ours: reward / optimum | condition | episodes | median decision (s) | "
             "depth reached | budget ran out |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name in ("Human (w/ time limit)", "Human (w/o time limit)"):
        lines.append(f"| {name} | {PAPER[name]} | | | | | | | |")
    for r in rows:
        paper = PAPER.get(r["model"], "-")
        count = f"{r['episodes']}"
        if r["expected"] and r["expected"] != r["episodes"]:
            count += f" of {r['expected']}"
        lines.append(f"| {r['model']} | {paper} | {mean_pm((r['reward'], r['sem']))} | "
                     f"{mean_pm((r['ratio'], r['ratio_sem']))} | "
                     f"{r['condition']} | {count} | {_two(r['decision_time'])} | "
                     f"{_two(r.get('depth', math.nan))} | {_share(r.get('ran_out', math.nan))} |")
    missing = [r for r in rows if r["status"] != "complete"]
    lines.append("")
    lines.append("Depth reached and budget ran out: over the decisions with at least the planner's depth of "
                 "blocks left, the mean depth its search completed and the share stopped by the budget.")
    lines.append("")
    fallback = sorted({r["job"] for r in rows if r.get("optimum_of") == "static" and not math.isnan(r["ratio"])})
    lines.append("Mean over all episodes; ± is the SEM across tasks (of each task's mean over its runs). "
                 "Reward / optimum divides by the task's optimum under the physics and resolution the job used "
                 "(`overhang_framework/data/optima.json`, computed by `python -m overhang_framework.optimum`)"
                 + (f"; for {', '.join(fallback)} that physics has no stored optimum for every task, and the "
                    "static physics' optimum stands in (an estimate)." if fallback else "."))
    if missing:
        lines.append("")
        lines.append("Not complete (rerun the same command to resume): "
                     + ", ".join(f"{r['job']} ({r['model']}: {r['status']}, {r['episodes']} episodes)"
                                 for r in missing) + ".")
    return "\n".join(lines) + "\n"


def _share(value: float) -> str:
    return "-" if value is None or math.isnan(value) else f"{100 * value:.0f}%"


def write(root: Path | str) -> tuple[Path, str]:
    """Write ``table2.md`` for the sweep under ``root``; return its path and text."""
    from overhang_framework.optimum import load_optima

    root = Path(root)
    jobs = load_jobs(root)
    if not jobs:
        raise FileNotFoundError(f"{root} holds no run (no run.json or .hydra/overrides.yaml below it)")
    text = render(rows_of(jobs, load_optima()), root)
    path = root / "table2.md"
    atomic_write_text(path, text)
    return path, text


class Table2Callback(SweepResults):
    """``results.csv`` as for every sweep, then Table 2 printed and written to ``table2.md`` (also when
    some jobs failed: the exit status is still 1 then)."""

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        if sweep_dir.is_dir():
            try:
                path, text = write(sweep_dir)
            except FileNotFoundError:
                path = None
            if path is not None:
                print(text, end="")
                print(f"table: {path}")
        super().on_multirun_end(config, **kwargs)


def main(argv: Optional[Sequence[str]] = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.report.table2",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", help="the sweep directory of experiment=table2 (or any sweep)")
    parser.add_argument("--json", type=Path, default=None,
                        help="also write each model's row (reward and its SEM across tasks, episodes, ...) to this file")
    args = parser.parse_args(argv)
    if not Path(args.dir).is_dir():
        print(f"error: {args.dir} is not a directory", file=sys.stderr)
        return 2
    try:
        path, text = write(args.dir)
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json is not None:
        from overhang_framework.optimum import load_optima
        from overhang_framework.results import atomic_write_json

        rows = rows_of(load_jobs(Path(args.dir)), load_optima())
        atomic_write_json(args.json, {"models": {r["model"]: r for r in rows}})
    print(text, end="")
    print(f"table: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
