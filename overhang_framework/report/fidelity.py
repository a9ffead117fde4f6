"""How the paper's Table 2 levels depend on the models' assumptions: a grid of Table 2 runs, and its table.

    python -m overhang_framework.fidelity run grid --out runs/fidelity/grid     # resumable
    python -m overhang_framework.fidelity run draws --out runs/fidelity/draws   # other draws of 20 tasks
    python -m overhang_framework.fidelity report runs/fidelity/grid            # fidelity.md, grid.csv, grid.png

A point set (``grid``, ``draws``, or a YAML file of your own) names points, each a few settings
(:data:`SETTINGS`) that differ from the paper's Table 2 (``experiment=table2``). ``run`` runs the
three models at every point as their own Table 2 sweep, ``OUT/<point>/<model>``, so a stopped run goes
on where it stopped and each model's wall time is kept beside it (``wall.json``). ``report`` reads the
episodes only: each model's terminal reward (mean over episodes, ± SEM across tasks, as Table 2), whether
it lies within the paper's SEM of the paper's value, whether the order myopic < D2 < D3 holds, and the
largest distance from the paper in the paper's SEMs (a point matches when that is at most 1 and the order
holds).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from overhang_framework.errors import ConfigError

#: The paper's Table 2 for the three models: (mean, SEM) of terminal reward over its 20 tasks.
PAPER = {"myopic": (0.52, 0.12), "lookahead_d2": (0.912, 0.10), "lookahead_d3": (1.180, 0.24)}
MODELS = tuple(PAPER)
LABELS = {"myopic": "Myopic", "lookahead_d2": "Lookahead (D=2)", "lookahead_d3": "Lookahead (D=3)"}


@dataclass(frozen=True)
class Setting:
    """One assumption a point can change: the override it becomes, and the models it applies to."""

    override: str
    help: str
    models: tuple[str, ...] = MODELS
    default: Any = None


#: The assumptions a point may set, by name.
SETTINGS = {
    "choice": Setting("planner.choice={}", "the planners' choice rule: argmax or softmax", default="argmax"),
    "beta": Setting("planner.beta={}", "softmax's inverse temperature, per metre of score", default=10.0),
    "cnn_bias": Setting("++predictor.late_params.bias={}", "the CNN's logit bias (> 0: calls towers standing "
                        "more often)", default=0.0),
    "cnn_temperature": Setting("++predictor.late_params.temperature={}", "the CNN's logit temperature "
                               "(< 1: overconfident)", default=1.0),
    "ipe_sigma": Setting("++predictor.early_params.sigma={}", "the IPE's noise scale", default=0.03),
    "ipe_K": Setting("++predictor.early_params.K={}", "the IPE's simulations per candidate", default=50),
    "switch": Setting("predictor.switch={}", "blocks from which the hybrid asks the CNN", default=4),
    "myopic_reward": Setting("planner.reward={}", "the myopic planner's immediate reward: overhang, gain or "
                             "final", models=("myopic",), default="overhang"),
    "tasks_seed": Setting("tasks.generator_seed={}", "another seeded draw of 20 tasks (tasks=draw)",
                          default=2025),
}


@dataclass
class Point:
    name: str
    settings: dict = field(default_factory=dict)
    overrides: list = field(default_factory=list)

    def overrides_for(self, model: str) -> list[str]:
        out = []
        if "tasks_seed" in self.settings:
            out.append("tasks=draw")
        for key, value in self.settings.items():
            setting = SETTINGS[key]
            if model in setting.models:
                out.append(setting.override.format(value))
        return out + [str(o) for o in self.overrides]

    def touches(self, model: str) -> bool:
        """Whether this point changes anything for ``model`` (else it shares the base point's run)."""
        return bool(self.overrides) or any(model in SETTINGS[k].models for k in self.settings)

    def value(self, key: str) -> Any:
        return self.settings.get(key, SETTINGS[key].default)


def load_points(source: str) -> tuple[list[Point], dict]:
    """The points of a named set shipped with the package (``grid``, ``draws``) or of a YAML file."""
    import yaml

    path = Path(source)
    if path.suffix in (".yaml", ".yml") or path.exists():
        if not path.is_file():
            raise ConfigError(f"point set {source}: no such file")
        text = path.read_text()
    else:
        shipped = resources.files("overhang_framework.conf") / "fidelity" / f"{source}.yaml"
        if not shipped.is_file():
            names = sorted(p.name[:-5] for p in (resources.files("overhang_framework.conf") / "fidelity").iterdir()
                           if p.name.endswith(".yaml"))
            raise ConfigError(f"unknown point set {source!r}; shipped: {', '.join(names)}, or a path to a .yaml file")
        text = shipped.read_text()
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"point set {source} is not valid YAML: {str(err).splitlines()[0]}") from None
    if not isinstance(data, dict) or not isinstance(data.get("points"), dict) or not data["points"]:
        raise ConfigError(f"point set {source} needs a mapping 'points: {{name: {{setting: value, ...}}}}'")
    points = []
    for name, spec in data["points"].items():
        spec = dict(spec or {})
        overrides = spec.pop("overrides", []) or []
        unknown = sorted(set(spec) - set(SETTINGS))
        if unknown:
            raise ConfigError(f"point {name} of {source}: unknown setting {unknown[0]!r}; allowed: "
                              f"{', '.join(SETTINGS)}, overrides")
        if not isinstance(overrides, list):
            raise ConfigError(f"point {name} of {source}: overrides must be a list of Hydra overrides")
        points.append(Point(str(name), spec, overrides))
    return points, {k: v for k, v in data.items() if k != "points"}


# --------------------------------------------------------------------------------------------- running

def _complete(directory: Path) -> bool:
    from overhang_framework.report.aggregate import job_dirs, job_row

    if not (directory / "results.csv").exists():
        return False
    rows = [job_row(p, directory) for p in job_dirs(directory)]
    return bool(rows) and all(r["status"] == "complete" for r in rows)


def command_for(point: Point, model: str, out: Path, repeats: int, jobs: int, seed: int,
                extra: Sequence[str] = ()) -> list[str]:
    return [sys.executable, "-m", "overhang_framework", "experiment=table2", f"model={model}",
            f"repeats={repeats}", f"jobs={jobs}", f"seed={seed}", "progress=false",
            *point.overrides_for(model), *extra, f"hydra.sweep.dir={out / point.name / model}"]


def run(points: Sequence[Point], out: Path, repeats: int, jobs: int, seed: int,
        models: Sequence[str] = MODELS, extra: Sequence[str] = (), only: Optional[Sequence[str]] = None) -> int:
    """Run every point's models that are not finished; returns the number of runs that failed."""
    by_name = {p.name: p for p in points}
    missing = [name for name in only or () if name not in by_name]
    if missing:
        raise ConfigError(f"unknown point {missing[0]!r}; points: {', '.join(by_name)}")
    wanted = [by_name[name] for name in dict.fromkeys(only)] if only else list(points)  # in the order asked
    base = base_point(points)
    todo = [(p, m) for p in wanted for m in models if p is base or base is None or p.touches(m)]
    failed = 0
    for n, (point, model) in enumerate(todo, 1):
        directory = out / point.name / model
        if _complete(directory):
            print(f"[{n}/{len(todo)}] {point.name} {model}: done before", flush=True)
            continue
        cmd = command_for(point, model, out, repeats, jobs, seed, extra)
        directory.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        print(f"[{n}/{len(todo)}] {point.name} {model}: {' '.join(cmd[2:])}", flush=True)
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        seconds = time.perf_counter() - start
        wall = directory / "wall.json"
        before = json.loads(wall.read_text()).get("seconds", 0.0) if wall.exists() else 0.0
        from overhang_framework.results import atomic_write_json

        atomic_write_json(wall, {"seconds": before + seconds, "command": " ".join(["python", *cmd[1:]])})
        if proc.returncode:
            failed += 1
            last = [line for line in proc.stdout.splitlines() if line.strip()][-1:] or ["(no output)"]
            print(f"    failed (exit {proc.returncode}) after {seconds:.0f} s: {last[0]}", flush=True)
        else:
            print(f"    {seconds:.0f} s", flush=True)
    return failed


# --------------------------------------------------------------------------------------------- report

def level(directory: Path) -> dict:
    """One model's Table 2 level at one point: reward, SEM across tasks, episodes, tasks, wall seconds."""
    from overhang_framework.report.build import load_jobs
    from overhang_framework.report.table2 import task_sem

    episodes = [e for job in load_jobs(directory) for e in job.episodes] if directory.exists() else []
    reward, sem, tasks = task_sem(episodes, [e["reward"] for e in episodes])
    stood = float(np.mean([bool(e.get("stable_throughout", e["reward"] > 0)) for e in episodes])) if episodes else math.nan
    wall = directory / "wall.json"
    seconds = json.loads(wall.read_text()).get("seconds") if wall.exists() else None
    return {"reward": reward, "sem": sem, "episodes": len(episodes), "tasks": tasks, "stood": stood,
            "seconds": seconds, "complete": _complete(directory)}


def assess(levels: dict) -> dict:
    """Distances from the paper in its SEMs, whether each model is within one, and whether the order holds."""
    out: dict = {}
    for model, (mean, sem) in PAPER.items():
        got = levels.get(model, {}).get("reward", math.nan)
        out[f"{model}_z"] = (got - mean) / sem if np.isfinite(got) else math.nan
        out[f"{model}_within"] = bool(np.isfinite(got) and abs(got - mean) <= sem)
    r = [levels.get(m, {}).get("reward", math.nan) for m in MODELS]
    out["order"] = bool(all(np.isfinite(r)) and r[0] < r[1] < r[2])
    zs = [abs(out[f"{m}_z"]) for m in MODELS]
    out["distance"] = max(zs) if all(np.isfinite(zs)) else math.nan
    out["match"] = bool(out["order"] and all(out[f"{m}_within"] for m in MODELS))
    return out


def base_point(points: Sequence[Point]) -> Optional[Point]:
    """The point that changes nothing (the paper's settings), if the set has one."""
    return next((p for p in points if not p.settings and not p.overrides), None)


def run_dir(points: Sequence[Point], point: Point, model: str, out: Path) -> Path:
    """Where ``point``'s ``model`` ran: its own directory, or the base point's when it changes nothing there."""
    base = base_point(points)
    owner = point if base is None or point.touches(model) else base
    return out / owner.name / model


def table(points: Sequence[Point], out: Path) -> list[dict]:
    rows = []
    for point in points:
        levels = {m: level(run_dir(points, point, m, out)) for m in MODELS}
        for m in MODELS:  # a shared run's time is the point's that ran it
            if run_dir(points, point, m, out) != out / point.name / m:
                levels[m]["seconds"] = None
        row: dict = {"point": point.name, **{k: point.value(k) for k in SETTINGS}}
        for m in MODELS:
            for key in ("reward", "sem", "stood", "episodes", "seconds", "complete"):
                row[f"{m}_{key}"] = levels[m][key]
        row.update(assess(levels))
        row["complete"] = all(levels[m]["complete"] for m in MODELS)
        rows.append(row)
    return rows


def _pm(mean: float, sem: float) -> str:
    if not np.isfinite(mean):
        return "not run"
    return f"{mean:.3f} ± {sem:.3f}" if np.isfinite(sem) else f"{mean:.3f}"


def changed(point: Point) -> str:
    parts = [f"{k}={v}" for k, v in point.settings.items()] + list(point.overrides)
    return ", ".join(parts) or "the paper's settings (as `experiment=table2`)"


def render(points: Sequence[Point], rows: Sequence[dict], title: str) -> str:
    by = {p.name: p for p in points}
    lines = [f"# {title}", "",
             "| point | settings | myopic | D2 | D3 | order | distance (paper SEMs) | match | wall (s) |",
             "|---|---|---|---|---|---|---|---|---|",
             "| **the paper** | | 0.52 ± 0.12 | 0.912 ± 0.10 | 1.180 ± 0.24 | yes | 0 | | |"]
    for r in rows:
        cells = []
        for m in MODELS:
            text = _pm(r[f"{m}_reward"], r[f"{m}_sem"])
            if np.isfinite(r[f"{m}_stood"]):
                text += f" ({r[f'{m}_stood']:.0%})"
            if np.isfinite(r[f"{m}_reward"]) and not r[f"{m}_complete"]:
                text += f", {r[f'{m}_episodes']} episodes so far"
            cells.append(f"**{text}**" if r[f"{m}_within"] else text)
        seconds = [r[f"{m}_seconds"] for m in MODELS if r[f"{m}_seconds"] is not None]
        wall = f"{sum(seconds):,.0f}" if seconds else ""
        partial = any(r[f"{m}_episodes"] and not r[f"{m}_complete"] for m in MODELS)
        note = " (unfinished)" if partial else ""
        known = np.isfinite(r["distance"])
        order = ("yes" if r["order"] else "no") if known else "—"
        distance = f"{r['distance']:.2f}" if known else "—"
        lines.append(f"| {r['point']}{note} | {changed(by[r['point']])} | {' | '.join(cells)} | "
                     f"{order} | {distance} | {'yes' if r['match'] else ''} | {wall} |")
    lines += ["", "Terminal reward, mean over episodes ± SEM across tasks (in brackets: the share of towers that "
              "stood to the end); bold: within the paper's SEM of the paper's value. Distance: the largest |ours − paper| / paper's SEM of the three models."]
    done = [r for r in rows if np.isfinite(r["distance"])]
    if done:
        best = min(done, key=lambda r: (not r["order"], r["distance"]))
        matches = [r["point"] for r in rows if r["match"]]
        lines += ["", (f"Points where all three levels lie within the paper's SEMs in the paper's order: "
                       f"{', '.join(matches)}." if matches else
                       "No point puts all three levels within the paper's SEMs in the paper's order.")
                  + f" Closest with the order: {best['point']} (distance {best['distance']:.2f})."]
    draws = [r for r in rows if "tasks_seed" in by[r["point"]].settings]
    if len(draws) > 1:
        lines += ["", "Across the draws of tasks:", ""]
        for m in MODELS:
            v = np.array([r[f"{m}_reward"] for r in draws if np.isfinite(r[f"{m}_reward"])])
            if v.size > 1:
                lines.append(f"- {LABELS[m]}: {v.min():.3f} to {v.max():.3f} over {v.size} draws, SD "
                             f"{v.std(ddof=1):.3f}; paper {PAPER[m][0]}")
    return "\n".join(lines) + "\n"


def figure(points: Sequence[Point], rows: Sequence[dict], x: str, lines_by: str, path: Path) -> Optional[Path]:
    """The three levels against setting ``x``, one line per value of ``lines_by``, at the points that
    change nothing else; the paper's value ± SEM as a band. ``None`` when no point qualifies."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import FixedFormatter, FixedLocator, NullLocator

    from overhang_framework.report.build import COLORS as COLOURS
    from overhang_framework.results import atomic_output

    by = {p.name: p for p in points}
    use = [r for r in rows if set(by[r["point"]].settings) <= {x, lines_by, "choice"} and not by[r["point"]].overrides]
    if not use:
        return None

    def xval(r):  # argmax plotted at beta = infinity, drawn at the right edge
        return math.inf if r["choice"] == "argmax" and x == "beta" else float(r[x])

    finite = sorted({xval(r) for r in use if np.isfinite(xval(r))})
    argmax = any(not np.isfinite(xval(r)) for r in use)
    edge = (finite[-1] * 1.6 if finite else 1.0)
    groups = sorted({_plain(r[lines_by]) for r in use}, key=lambda v: (isinstance(v, str), v))
    colours = {g: COLOURS[i % len(COLOURS)] for i, g in enumerate(groups)}
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8), sharey=True)
    for ax, m in zip(axes, MODELS):
        mean, sem = PAPER[m]
        ax.axhspan(mean - sem, mean + sem, color="0.88", zorder=0)
        ax.axhline(mean, color="0.45", lw=1, zorder=1)
        for g in groups:
            pts = sorted((xval(r) if np.isfinite(xval(r)) else edge, r[f"{m}_reward"], r[f"{m}_sem"])
                         for r in use if _plain(r[lines_by]) == g and np.isfinite(r[f"{m}_reward"])
                         and r.get(f"{m}_complete", True))
            if pts:
                xs, ys, es = zip(*pts)
                ax.errorbar(xs, ys, yerr=es, marker="o", ms=4, capsize=2, color=colours[g])
        ax.set_title(LABELS[m], fontsize=10)
        if x == "beta":
            ax.set_xscale("log")
        shown: list = []  # tick labels that do not overlap: each at least 18% beyond the last
        for t in finite:
            if not shown or t / shown[-1] >= 1.18:
                shown.append(t)
        ticks = shown + ([edge] if argmax and x == "beta" else [])
        ax.xaxis.set_major_locator(FixedLocator(ticks))
        ax.xaxis.set_major_formatter(FixedFormatter([f"{t:g}" for t in shown] + (["argmax"] if len(ticks) > len(shown)
                                                                                  else [])))
        ax.xaxis.set_minor_locator(NullLocator())
        ax.tick_params(axis="x", labelsize=8)
        ax.set_xlabel(x)
    handles = [Patch(color="0.88", label="paper ± SEM")] + [Line2D([], [], color=colours[g], marker="o", ms=4,
                                                                   label=f"{lines_by} = {g:g}" if isinstance(g, (int, float)) else f"{lines_by} = {g}")
                                                            for g in groups]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    axes[0].set_ylabel("terminal reward (paper20)")
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    plt.close(fig)
    return path


def _plain(value):
    """A setting's value for grouping: numbers as floats (1 and 1.0 are one group), anything else as is."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else value


def report(out: Path, source: str, x: Optional[str] = None, lines_by: Optional[str] = None) -> str:
    from overhang_framework.results import atomic_output, atomic_write_text

    points, meta = load_points(source)
    rows = table(points, out)
    text = render(points, rows, str(meta.get("title", f"Table 2 levels over the points of {source}")))
    atomic_write_text(out / "fidelity.md", text)
    import csv

    with atomic_output(out / "grid.csv") as tmp:
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    x = x or meta.get("x")
    lines_by = lines_by or meta.get("lines")
    if x and lines_by:
        figure(points, rows, x, lines_by, out / "grid.png")
    return text


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.fidelity", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run the points' Table 2 models that are not finished")
    r.add_argument("points", help="grid, draws, or a YAML file of points")
    r.add_argument("--out", required=True, type=Path)
    r.add_argument("--repeats", type=int, default=5, help="runs per task of each model (default 5)")
    r.add_argument("--jobs", type=int, default=2, help="processes per model (default 2)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    r.add_argument("--only", nargs="+", help="these points only")
    r.add_argument("--override", nargs="*", default=[], help="more Hydra overrides for every run")
    p = sub.add_parser("report", help="the table, grid.csv and the figure of a run's directory")
    p.add_argument("out", type=Path)
    p.add_argument("--points", default=None, help="the point set it ran (default: points.txt in OUT)")
    p.add_argument("--x", default=None, choices=list(SETTINGS))
    p.add_argument("--lines", default=None, choices=list(SETTINGS))
    args = parser.parse_args(argv)
    try:
        if args.command == "run":
            if args.repeats < 1 or args.jobs < 1:
                raise ConfigError("--repeats and --jobs must be whole numbers >= 1")
            points, _ = load_points(args.points)
            args.out.mkdir(parents=True, exist_ok=True)
            from overhang_framework.results import atomic_write_text

            atomic_write_text(args.out / "points.txt", str(Path(args.points).resolve()) if Path(args.points).exists()
                              else args.points)
            failed = run(points, args.out, args.repeats, args.jobs, args.seed, args.models, args.override, args.only)
            print(report(args.out, (args.out / "points.txt").read_text()))
            return 1 if failed else 0
        source = args.points or ((args.out / "points.txt").read_text() if (args.out / "points.txt").exists() else None)
        if source is None:
            raise ConfigError(f"{args.out} has no points.txt; name the point set with --points")
        print(report(args.out, source, args.x, args.lines))
        return 0
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
