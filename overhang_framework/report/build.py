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
* by placement, the overhang of the towers standing and the share of episodes
  standing (``steps.png``);
* decision time and search depth completed by placement (``effort.png``);
* the towers every job built for one task, in task units, with the ground, the
  ground block's edges and the overhang marked (``towers.png``).

Rerunning it on the same results writes the same files.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Sequence, Union

import numpy as np

from overhang_framework.report.aggregate import job_dirs, job_row
from overhang_framework.results import atomic_output, atomic_write_text, mean_sem

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from overhang_framework.geometry import Geometry

FIGURES = ("reward.png", "steps.png", "effort.png", "towers.png")
FONT = 10  # points: tick and axis labels, panel titles
SMALL = 9  # points: legends, tower panel titles and labels
COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray",
          "tab:olive", "tab:cyan")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
LINESTYLES: tuple[Union[str, tuple], ...] = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)))
STOOD, FELL, MARK = "tab:blue", "tab:red", "tab:green"  # towers that stood, that fell; the overhang

Point = tuple[float, float, int]  # mean, SEM (NaN for fewer than two values), number of values


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


def _point(values: list[float]) -> Point:
    mean, sem = mean_sem(values)
    return mean, sem, len(values)


def _placements(episodes: list[dict]) -> int:
    return max((len(e["sequence"]) - 1 for e in episodes), default=0)


def overhang_standing(episodes: list[dict]) -> list[Point]:
    """Per placement (0-based), the overhang of the towers standing after it.

    A tower that fell at that placement, or earlier, is left out: its overhang is
    the one of blocks on their way down.
    """
    return [_point([e["steps"][k]["overhang"] for e in episodes
                    if len(e["steps"]) > k and e["steps"][k]["stable"]])
            for k in range(_placements(episodes))]


def share_standing(episodes: list[dict]) -> list[Point]:
    """Per placement (0-based), the share of the episodes whose tower stands after it.

    Every episode whose sequence has that placement counts; one that collapsed
    earlier (a collapse ends an episode) counts as fallen.
    """
    out = []
    for k in range(_placements(episodes)):
        shares = [float(len(e["steps"]) > k and bool(e["steps"][k]["stable"])) for e in episodes
                  if len(e["sequence"]) - 1 > k and (len(e["steps"]) > k or not e["stable_throughout"])]
        out.append(_point(shares))
    return out


def decision_time_by_step(episodes: list[dict]) -> list[Point]:
    """Per placement (0-based), the decision time (s) of the placements made."""
    return [_point([e["steps"][k]["decision_time"] for e in episodes if len(e["steps"]) > k])
            for k in range(_placements(episodes))]


def depth_by_step(episodes: list[dict]) -> list[Point]:
    """Per placement (0-based), the search depth completed where the planner reports one."""
    out = []
    for k in range(_placements(episodes)):
        depths = [e["steps"][k]["spend"].get("depth_completed") for e in episodes if len(e["steps"]) > k]
        out.append(_point([float(d) for d in depths if d is not None]))
    return out


def y_limits(points: Sequence[Point], floor: Optional[float] = None, integer: bool = False) -> tuple[float, float]:
    """A y range that shows every mean ± SEM of ``points``, starts at ``floor`` when given (and below
    every value), and stays open for a constant series: half a unit of headroom for ``integer`` data,
    10% of the span (or of the value, for a constant series) otherwise."""
    ends = []
    for mean, sem, _ in points:
        if math.isnan(mean):
            continue
        spread = 0.0 if math.isnan(sem) else sem
        ends += [mean - spread, mean + spread]
    if not ends:
        return (0.0, 1.0) if floor is None else (floor, floor + 1.0)
    lo, hi = min(ends), max(ends)
    if floor is not None:
        lo = min(lo, floor)
    span = hi - lo
    if integer:
        pad = 0.5
    elif span > 1e-9:
        pad = 0.1 * span
    else:
        pad = max(0.1 * abs(hi), 0.05)
    bottom = floor if floor is not None and lo >= floor else lo - pad
    return bottom, hi + pad


@dataclass(frozen=True)
class Style:
    """How one condition is drawn, the same in every panel."""

    color: str
    marker: str
    linestyle: Union[str, tuple]
    dodge: float  # horizontal offset of its points, in placements


def styles(n: int) -> list[Style]:
    """Distinct colour, marker and line style for each of ``n`` conditions, and a horizontal dodge
    that keeps conditions with equal values apart (at most ±0.2 placement)."""
    step = 0.0 if n < 2 else min(0.08, 0.4 / (n - 1))
    return [Style(COLORS[i % len(COLORS)], MARKERS[i % len(MARKERS)], LINESTYLES[i % len(LINESTYLES)],
                  (i - (n - 1) / 2) * step) for i in range(n)]


def identical(series: dict[str, list[Point]]) -> list[list[str]]:
    """Groups of two or more keys whose series have the same means (to 1e-9)."""
    groups: list[list[str]] = []
    means = {k: [p[0] for p in v] for k, v in series.items() if v}
    for key, values in means.items():
        for group in groups:
            other = means[group[0]]
            if len(other) == len(values) and all(
                    (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9 for a, b in zip(other, values)):
                group.append(key)
                break
        else:
            groups.append([key])
    return [g for g in groups if len(g) > 1]


def _series_panel(ax: Axes, jobs: list[Job], series: list[list[Point]], ylabel: str, title: str,
                  limits: tuple[float, float], integer: bool = False) -> None:
    """One line per job over the placements, dodged and styled by :func:`styles`."""
    from matplotlib.ticker import MaxNLocator

    for i, (job, points, style) in enumerate(zip(jobs, series, styles(len(jobs)))):
        if not points or all(math.isnan(p[0]) for p in points):
            continue
        k = np.arange(1, len(points) + 1) + style.dodge
        m = np.array([p[0] for p in points], dtype=float)
        s = np.array([0.0 if math.isnan(p[1]) else p[1] for p in points])
        ax.errorbar(k, m, yerr=s, color=style.color, marker=style.marker, linestyle=style.linestyle, ms=6, lw=1.6,
                    capsize=3, mfc="white" if i % 2 else style.color, label=_legend_label(job))
    same = identical({j.name: p for j, p in zip(jobs, series)})
    if same:
        title += "\n" + "; ".join(" = ".join(g) for g in same) + ": identical values"
    longest = max((len(p) for p in series), default=1) or 1
    ax.set_xticks(np.arange(1, longest + 1))
    ax.set_xlim(0.5, longest + 0.5)
    ax.set_xlabel("placement", fontsize=FONT)
    ax.set_ylabel(ylabel, fontsize=FONT)
    ax.set_title(title, fontsize=FONT)
    ax.set_ylim(*limits)
    if integer:
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.tick_params(labelsize=FONT)
    ax.grid(alpha=0.3)


def _legend_label(job: Job) -> str:
    return f"{job.name}: {job.label}"


def _figure_legend(fig: Figure, axes: Sequence[Axes]) -> None:
    """One legend for every panel, below them."""
    handles, labels = [], []
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    if handles:
        ncol = 1 if max(len(lab) for lab in labels) > 60 else min(2, len(labels))
        fig.legend(handles, labels, loc="outside lower center", ncol=ncol, fontsize=SMALL, frameon=False)


def reward_figure(rows: list[dict], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4.5, 1.3 * len(rows) + 2), 4.2), layout="constrained")
    x = np.arange(len(rows))
    means = [r["reward"][0] if not math.isnan(r["reward"][0]) else 0 for r in rows]
    sems = [0 if (r["reward"][1] is None or math.isnan(r["reward"][1])) else r["reward"][1] for r in rows]
    ax.bar(x, means, yerr=sems, color="tab:blue", alpha=0.8, capsize=3)
    ax.set_xticks(x, [f"{r['job']}\n{r['label'].replace(' / ', chr(10))}" for r in rows], fontsize=SMALL)
    ax.set_ylabel("terminal reward (mean ± SEM)", fontsize=FONT)
    ax.tick_params(axis="y", labelsize=FONT)
    ax.grid(axis="y", alpha=0.3)
    _save(fig, path)
    plt.close(fig)


def steps_plot(jobs: list[Job]) -> Figure:
    """Overhang of the standing towers and the share standing, by placement (a matplotlib Figure)."""
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    overhang = [overhang_standing(j.episodes) for j in jobs]
    _series_panel(a, jobs, overhang, "overhang after the placement",
                  "Overhang of the towers standing after the placement\n(mean ± SEM; towers that fell are left out)",
                  y_limits([p for s in overhang for p in s]))
    standing = [share_standing(j.episodes) for j in jobs]
    _series_panel(b, jobs, standing, "share of episodes",
                  "Towers standing after the placement\n(an episode that collapsed counts as fallen from then on)",
                  (-0.05, 1.05))
    _figure_legend(fig, (a, b))
    return fig


def effort_plot(jobs: list[Job]) -> Figure:
    """Decision time and the search depth completed, by placement (a matplotlib Figure)."""
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    times = [decision_time_by_step(j.episodes) for j in jobs]
    _series_panel(a, jobs, times, "decision time (s)", "Decision time per placement\n(mean ± SEM)",
                  y_limits([p for s in times for p in s], floor=0.0))
    depths = [depth_by_step(j.episodes) for j in jobs]
    _series_panel(b, jobs, depths, "search depth completed (placements)",
                  "Search depth completed\n(at most the blocks left to place)",
                  y_limits([p for s in depths for p in s], floor=0.0, integer=True), integer=True)
    _figure_legend(fig, (a, b))
    return fig


def steps_figure(jobs: list[Job], path: Path) -> None:
    fig = steps_plot(jobs)
    _save(fig, path)
    _plt().close(fig)


def effort_figure(jobs: list[Job], path: Path) -> None:
    fig = effort_plot(jobs)
    _save(fig, path)
    _plt().close(fig)


def tower_of(episode: dict) -> Geometry:
    """The last tower an episode built (the one that fell, if it collapsed), as a Geometry."""
    from overhang_framework.geometry import Block, Geometry

    blocks = [Block(float(episode["sequence"][0]), 0.0, 0)]
    blocks += [Block(float(s["width"]), float(s["x"]), int(s["layer"])) for s in episode["steps"]]
    return Geometry(tuple(blocks))


def _outcome(episode: dict, overhang: float) -> str:
    if episode["stable_throughout"]:
        return f"stood: overhang {overhang:.2f} (the reward)"
    return f"fell at placement {len(episode['steps'])}: overhang {overhang:.2f}, reward 0"


def towers_plot(jobs: list[Job], task_id: str) -> tuple[Optional[Figure], int]:
    """The tower each job built for ``task_id`` (its first episode of that task) on axes in task units,
    with the ground, the ground block's edges and the overhang marked; ``(Figure, panels)``, or
    ``(None, 0)`` when no job played the task."""
    from overhang_framework.geometry import BLOCK_HEIGHT, overhang

    built = []
    for job in jobs:
        episode = next((e for e in job.episodes if e["task_id"] == task_id), None)
        if episode is not None:
            built.append((job, tower_of(episode), episode))
    if not built:
        return None, 0
    plt = _plt()
    top = max(b.layer + 1 for _, g, _ in built for b in g.blocks) * BLOCK_HEIGHT
    z_max = top + 1.2
    cols = min(3, len(built))
    rows = math.ceil(len(built) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, rows * (0.48 * (z_max + 0.3) + 1.3) + 1.1),
                             squeeze=False, layout="constrained")
    for ax in axes.flat[len(built):]:
        ax.set_axis_off()
    for ax, (job, geometry, episode) in zip(axes.flat, built):
        fell = not episode["stable_throughout"]
        draw_tower(ax, geometry, fell=fell, z_max=z_max)
        ax.set_title(f"{_legend_label(job)}\n{_outcome(episode, overhang(geometry))}", fontsize=SMALL,
                     color="tab:red" if fell else "black")
    fig.suptitle(f"Towers built for {task_id} (each job's first episode of it)", fontsize=FONT + 1)
    fig.legend(handles=_tower_legend(any(not e["stable_throughout"] for _, _, e in built)),
               loc="outside lower center", ncol=3, fontsize=SMALL, frameon=False)
    return fig, len(built)


def _tower_legend(any_fell: bool) -> list:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=STOOD, edgecolor="black", label="tower that stood")]
    if any_fell:
        handles.append(Patch(facecolor=FELL, edgecolor="black", label="tower that fell"))
    return handles + [
        Line2D([], [], color="black", lw=2.5, label="ground (z = 0)"),
        Line2D([], [], color="0.35", lw=1.2, ls=":", label="edges of the ground block (the support)"),
        Line2D([], [], color="0.35", lw=1.0, ls="-.", label="x = 0: overhang is measured from here"),
        Line2D([], [], color=MARK, lw=1.5, ls="--", label="overhang: furthest block edge from x = 0"),
    ]


def draw_tower(ax: Axes, geometry: Geometry, fell: bool = False, z_max: Optional[float] = None) -> None:
    """A tower on a matplotlib axis in task units: the blocks, the ground, the ground block's edges,
    x = 0 and the overhang (the block edge furthest from x = 0), on the grid's x range."""
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MultipleLocator

    from overhang_framework.geometry import BLOCK_HEIGHT, GRID_HALF_WIDTH, overhang

    blocks = geometry.blocks
    top = max((b.layer + 1 for b in blocks), default=1) * BLOCK_HEIGHT
    z_max = z_max if z_max is not None else top + 1.2
    ax.axhspan(-0.3, 0, color="0.85", lw=0)
    ax.axhline(0, color="black", lw=2.5)
    for b in blocks:
        ax.add_patch(Rectangle((b.left, b.layer * BLOCK_HEIGHT), b.width, BLOCK_HEIGHT,
                               facecolor=FELL if fell else STOOD, edgecolor="black", lw=0.8, alpha=0.85))
    if blocks:
        ground = blocks[0]
        for x in (ground.left, ground.right):
            ax.axvline(x, color="0.35", lw=1.2, ls=":")
        ax.axvline(0, color="0.35", lw=1.0, ls="-.")
        reach = overhang(geometry)
        far = max(blocks, key=lambda b: abs(b.x) + b.width / 2)
        edge = reach if far.x >= 0 else -reach
        ax.axvline(edge, color=MARK, lw=1.5, ls="--")
        z = top + 0.35
        ax.annotate("", xy=(edge, z), xytext=(0, z),
                    arrowprops={"arrowstyle": "<|-|>", "color": MARK, "lw": 1.5, "shrinkA": 0, "shrinkB": 0})
        ax.text(edge / 2, z + 0.12, f"{reach:.2f}", color=MARK, ha="center", va="bottom", fontsize=SMALL,
                fontweight="bold")
    ax.set_xlim(-GRID_HALF_WIDTH, GRID_HALF_WIDTH)
    ax.set_ylim(-0.3, z_max)
    ax.set_aspect("equal")
    ax.xaxis.set_major_locator(MultipleLocator(1.0))
    ax.xaxis.set_minor_locator(MultipleLocator(0.2))
    ax.yaxis.set_major_locator(MultipleLocator(2 * BLOCK_HEIGHT))
    ax.yaxis.set_minor_locator(MultipleLocator(BLOCK_HEIGHT))
    ax.grid(axis="x", which="major", alpha=0.35)
    ax.grid(axis="x", which="minor", alpha=0.12)
    ax.tick_params(labelsize=SMALL)
    ax.set_xlabel("x (task units; grid spans -4 to 4)", fontsize=SMALL)
    ax.set_ylabel("height z", fontsize=SMALL)


def towers_figure(jobs: list[Job], task_id: str, path: Path) -> int:
    """The tower each job built for ``task_id`` (its first episode of that task); returns how many."""
    fig, n = towers_plot(jobs, task_id)
    if fig is not None:
        _save(fig, path)
        _plt().close(fig)
    return n


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
                  "Left: the overhang after each placement, mean ± SEM over the towers standing after it "
                  "(a tower that fell is left out). Right: the share of episodes whose tower stands after "
                  "each placement (a collapse ends an episode, so it counts as fallen from then on). Each job "
                  "has its own marker and line style and is shifted slightly along x, so equal values stay "
                  "visible; panel titles name jobs with identical values.", "", "![steps](steps.png)", "",
                  "Decision time per placement (mean ± SEM) and the search depth the planner completed "
                  "(at most the blocks left to place), over the placements made:", "", "![effort](effort.png)",
                  "", f"## Towers built for {task}", "",
                  f"{n} job(s) played {task}; each panel is a job's first episode of it, in task units. The "
                  "overhang is the block edge furthest from x = 0, the centre of the ground block.", "",
                  "![towers](towers.png)"]
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
