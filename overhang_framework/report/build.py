"""``report.md`` and its figures for a run or sweep directory.

    python -m overhang_framework.report DIR [--task paper00] [--out DIR]

The report reads only what runs wrote (``run.json``, ``episodes.jsonl`` or its
``.partial``, ``metrics.json``), so it works on a partial sweep, a sweep still
running, and jobs that ran on other machines; it says which jobs are missing,
unfinished or failed. It contains:

* a table in the paper's style, one row per job: terminal reward mean ± SEM,
  successful episodes, overhang of the successful ones, decision time, and
  reward / optimum where the task's optimum is known
  (``python -m overhang_framework.optimum`` keeps them);
* terminal reward by predictor × planner × condition (``reward.png``);
* overhang and stability by step (``steps.png``);
* decision time and search depth reached by step (``effort.png``);
* the towers every job built for one task (``towers.png``).

Rerunning it on the same results writes the same files.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.report.aggregate import job_dirs, job_row
from overhang_framework.results import atomic_output, atomic_write_text, mean_sem

FIGURES = ("reward.png", "steps.png", "effort.png", "towers.png")


@dataclass
class Job:
    """One run's results as the report needs them."""

    name: str
    path: Path
    status: str
    error: str
    config: dict
    episodes: list = field(default_factory=list)
    expected: Optional[int] = None

    @property
    def label(self) -> str:
        c = self.config
        parts = [str(c.get("predictor", {}).get("name", "?")), _planner_label(c.get("planner", {})),
                 str(c.get("condition", {}).get("name", "?"))]
        return " / ".join(parts)


def _planner_label(planner: dict) -> str:
    name = str(planner.get("name", "?"))
    return f"{name} D={planner['depth']}" if "depth" in planner else name


def load_jobs(root: Path) -> list[Job]:
    jobs = []
    for path in job_dirs(root):
        row = job_row(path, root)
        config = {}
        if (path / "run.json").exists():
            try:
                config = json.loads((path / "run.json").read_text()).get("config", {})
            except ValueError:
                pass
        episodes = []
        for name in ("episodes.jsonl", "episodes.jsonl.partial"):
            if (path / name).exists():
                for line in (path / name).read_text().splitlines():
                    try:
                        episodes.append(json.loads(line))
                    except ValueError:
                        break  # a line cut short by a crash
        expected = row.get("episodes_expected")
        status = row["status"]
        if status == "missing" and episodes:
            status = "incomplete"
        jobs.append(Job(row["job"], path, status, row.get("error", ""), config, episodes, expected))
    return jobs


def optimum_of(job: Job, episode: dict, optima: dict) -> Optional[float]:
    from overhang_framework.optimum import optimum_key_for

    world = job.config.get("world")
    if not world:
        return None
    row = optima.get(optimum_key_for(episode["sequence"], world))
    return None if row is None else float(row["optimum"])


def job_table(jobs: list[Job], optima: dict) -> tuple[str, list[dict]]:
    header = ("| job | predictor / planner / condition | episodes | terminal reward | successful | "
              "overhang (successful) | decision time (s) | reward / optimum |")
    lines = [header, "|" + "---|" * 8]
    rows = []
    for job in jobs:
        eps = job.episodes
        reward = mean_sem([e["reward"] for e in eps])
        success = mean_sem([float(e["stable_throughout"]) for e in eps])
        overhang = mean_sem([e["overhang"] for e in eps if e["stable_throughout"]])
        time_ = mean_sem([s["decision_time"] for e in eps for s in e["steps"]])
        ratios = []
        for e in eps:
            best = optimum_of(job, e, optima)
            if best:
                ratios.append(e["reward"] / best)
        ratio = mean_sem(ratios) if len(ratios) == len(eps) and eps else (math.nan, math.nan)
        count = f"{len(eps)}" + (f" of {job.expected}" if job.expected and job.expected != len(eps) else "")
        lines.append(f"| {job.name} | {job.label} | {count} | {mean_pm(reward)} | {mean_pm(success)} | "
                     f"{mean_pm(overhang)} | {mean_pm(time_)} | {mean_pm(ratio)} |")
        rows.append({"job": job.name, "label": job.label, "reward": reward, "ratio": ratio, "config": job.config})
    return "\n".join(lines), rows


def mean_pm(pair: tuple[float, float]) -> str:
    """``mean ± sem`` with 3 decimals; ``mean`` alone without a SEM; ``-`` without a mean."""
    mean, sem = pair
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "-"
    if sem is None or (isinstance(sem, float) and math.isnan(sem)):
        return f"{mean:.3f}"
    return f"{mean:.3f} ± {sem:.3f}"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams["svg.hashsalt"] = "overhang"
    return plt


def _save(fig, path: Path) -> None:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None})


def reward_figure(rows: list[dict], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(rows) + 2), 3.6))
    x = np.arange(len(rows))
    means = [r["reward"][0] if not math.isnan(r["reward"][0]) else 0 for r in rows]
    sems = [0 if (r["reward"][1] is None or math.isnan(r["reward"][1])) else r["reward"][1] for r in rows]
    ax.bar(x, means, yerr=sems, color="tab:blue", alpha=0.8, capsize=3)
    ax.set_xticks(x, [f"{r['job']}\n{r['label'].replace(' / ', chr(10))}" for r in rows], fontsize=7)
    ax.set_ylabel("terminal reward (mean ± SEM)")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def _by_step(jobs: list[Job], field_fn) -> dict[str, list[tuple[float, float]]]:
    out = {}
    for job in jobs:
        steps = max((len(e["steps"]) for e in job.episodes), default=0)
        out[f"{job.name}: {job.label}"] = [mean_sem([field_fn(e, k) for e in job.episodes if len(e["steps"]) > k])
                                           for k in range(steps)]
    return out


def _lines(ax, series: dict, ylabel: str) -> None:
    for label, points in series.items():
        if not points:
            continue
        k = np.arange(1, len(points) + 1)
        m = np.array([p[0] for p in points], dtype=float)
        s = np.array([0.0 if p[1] is None or math.isnan(p[1]) else p[1] for p in points])
        ax.errorbar(k, m, yerr=s, marker="o", ms=3, capsize=2, label=label)
    ax.set_xlabel("placement")
    ax.set_ylabel(ylabel)
    longest = max((len(p) for p in series.values()), default=0)
    ax.set_xticks(np.arange(1, longest + 1))
    ax.grid(alpha=0.3)


def steps_figure(jobs: list[Job], path: Path) -> None:
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    _lines(a, _by_step(jobs, lambda e, k: e["steps"][k]["overhang"]), "overhang after the placement")
    _lines(b, _by_step(jobs, lambda e, k: float(e["steps"][k]["stable"])), "share standing")
    b.set_ylim(-0.05, 1.05)
    b.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def effort_figure(jobs: list[Job], path: Path) -> None:
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    _lines(a, _by_step(jobs, lambda e, k: e["steps"][k]["decision_time"]), "decision time (s)")
    _lines(b, _by_step(jobs, lambda e, k: e["steps"][k]["spend"].get("depth_completed") or 0),
           "search depth completed")
    b.legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def towers_figure(jobs: list[Job], task_id: str, path: Path) -> int:
    """The tower each job built for ``task_id`` (its first episode of that task); returns how many."""
    from overhang_framework.geometry import Block, Geometry

    built = []
    for job in jobs:
        episode = next((e for e in job.episodes if e["task_id"] == task_id), None)
        if episode is None:
            continue
        blocks = [Block(float(episode["sequence"][0]), 0.0, 0)]
        for step in episode["steps"]:
            blocks.append(Block(float(step["width"]), float(step["x"]), int(step["layer"])))
        built.append((job, Geometry(tuple(blocks)), episode))
    if not built:
        return 0
    plt = _plt()
    cols = min(4, len(built))
    rows = math.ceil(len(built) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (job, geometry, episode) in zip(axes.flat, built):
        draw_tower(ax, geometry, fell=not episode["stable_throughout"])
        ax.set_title(f"{job.name}: {job.label}\nreward {episode['reward']:.2f}", fontsize=7)
    fig.suptitle(f"towers built for {task_id}", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return len(built)


def draw_tower(ax, geometry, fell: bool = False) -> None:
    """A tower on a matplotlib axis, through the project's renderer when it is installed."""
    try:
        from overhang_framework.render import draw_on_axes
    except ImportError:
        draw_on_axes = None
    if draw_on_axes is not None:
        draw_on_axes(ax, geometry, fell=fell)
        return
    from matplotlib.patches import Rectangle

    from overhang_framework.geometry import BLOCK_HEIGHT, GRID_HALF_WIDTH

    for b in geometry.blocks:
        ax.add_patch(Rectangle((b.left, b.layer * BLOCK_HEIGHT), b.width, BLOCK_HEIGHT,
                               facecolor="tab:red" if fell else "tab:blue", edgecolor="black", lw=0.6, alpha=0.85))
    ax.axhline(0, color="black", lw=0.8)
    ax.set_xlim(-GRID_HALF_WIDTH, GRID_HALF_WIDTH)
    ax.set_ylim(0, 5)
    ax.set_aspect("equal")


def build(root: Path | str, out: Optional[Path | str] = None, task: Optional[str] = None) -> Path:
    """Write ``report.md`` and its figures for the results under ``root``; return the report's path."""
    from overhang_framework.optimum import load_optima

    root = Path(root)
    out = Path(out) if out is not None else root
    jobs = load_jobs(root)
    if not jobs:
        raise FileNotFoundError(f"{root} holds no run (no run.json or .hydra/overrides.yaml below it)")
    optima = load_optima()
    table, rows = job_table(jobs, optima)
    with_episodes = [j for j in jobs if j.episodes]
    lines = [f"# Report: {root}", ""]
    counts = {}
    for job in jobs:
        counts[job.status] = counts.get(job.status, 0) + 1
    lines.append(f"{len(jobs)} job{'s' if len(jobs) != 1 else ''}: "
                 + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + ".")
    problems = [j for j in jobs if j.status != "complete"]
    if problems:
        lines += ["", "Not complete (rerun the same command to resume):", ""]
        for job in problems:
            what = f"{job.status}" + (f": {job.error}" if job.error else "")
            lines.append(f"- `{job.name}` ({job.label}): {what}, {len(job.episodes)} episodes finished")
    lines += ["", "## Terminal reward", "", table, ""]
    if any(not math.isnan(r["ratio"][0]) for r in rows):
        lines.append("Reward / optimum uses the optima of `overhang_framework/data/optima.json` "
                     "(same physics and resolution as the job).")
    else:
        lines.append("No optimum is known for these tasks under these physics settings "
                     "(`python -m overhang_framework.optimum` computes them).")
    if with_episodes:
        reward_figure([r for r, j in zip(rows, jobs) if j.episodes], out / "reward.png")
        steps_figure(with_episodes, out / "steps.png")
        effort_figure(with_episodes, out / "effort.png")
        task = task or with_episodes[0].episodes[0]["task_id"]
        n = towers_figure(with_episodes, task, out / "towers.png")
        lines += ["", "![terminal reward](reward.png)", "", "## By placement", "",
                  "Overhang after each placement and the share of towers standing:", "", "![steps](steps.png)", "",
                  "Decision time and the search depth completed:", "", "![effort](effort.png)", "",
                  f"## Towers built for {task}", "", f"{n} job(s) played {task}:", "", "![towers](towers.png)"]
    lines += ["", f"Made by `python -m overhang_framework.report {root}`."]
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def main(argv: Optional[Sequence[str]] = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", help="a run directory or a sweep directory")
    parser.add_argument("--out", default=None, help="where report.md and the figures go (default: DIR)")
    parser.add_argument("--task", default=None, help="the task whose towers are drawn (default: the first)")
    args = parser.parse_args(argv)
    if not Path(args.dir).is_dir():
        print(f"error: {args.dir} is not a directory", file=sys.stderr)
        return 2
    try:
        path = build(args.dir, args.out, args.task)
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"report: {path}")
    return 0
