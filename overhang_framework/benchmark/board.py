"""The leaderboard's file: its rows, how a finished run becomes one, and how the board is shown
(:mod:`overhang_framework.benchmark.leaderboard` is its command; :mod:`overhang_framework.benchmark.rerun`
scores its rows again)."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.version import __version__, commit

DATA_FILE = Path(__file__).resolve().parent.parent / "data" / "leaderboard.csv"
NO_CALLS = 0.5
#: The splits the leaderboard ranks, in its order.
SPLITS = ("test", "cross", "paper20", "train")
COLUMNS = ("agent", "split", "score", "ci_low", "ci_high", "stood", "reward", "area", "n_tasks", "seeds",
           "budget_kind", "calls_per_decision", "seconds_per_decision", "wall_seconds", "jobs", "curve", "physics",
           "command", "config", "version", "commit", "date")


def command_of(run_dir: Path) -> str:
    """The command that made ``run_dir``: its Hydra overrides, less the run directory, the progress bar and the
    verdict cache's path (where a machine keeps its verdicts changes no score)."""
    import yaml

    path = run_dir / ".hydra" / "overrides.yaml"
    words = yaml.safe_load(path.read_text()) if path.exists() else []
    words = [w for w in words if not w.startswith(("hydra.run.dir=", "progress=", "verdicts="))]
    quoted = [f"'{w}'" if any(c in w for c in "[]{},") else w for w in words]
    return " ".join(["python -m overhang_framework.benchmark", *quoted])


def row_of(run_dir: Path, agent: Optional[str] = None, wall: Optional[float] = None, jobs: Optional[int] = None) -> dict:
    """The leaderboard row of the finished run in ``run_dir``; ``wall`` (seconds, every sitting of the run added up)
    and ``jobs`` (episodes played at once) when known, as ``rerun`` knows them."""
    path = run_dir / "summary.json"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir} has no summary.json; is it a finished benchmark run?")
    s = json.loads(path.read_text())
    if s.get("split") not in SPLITS:
        raise ValueError(f"{run_dir} played {'a list of task ids (ids=[...])' if s.get('split') == 'ids' else repr(s.get('split'))}"
                         f", not a split; the leaderboard ranks whole splits: {', '.join(SPLITS)}")
    if s.get("score") is None:
        raise ValueError(f"{run_dir} has no score: none of its tasks has an optimum under its physics; "
                         "rescore it (python -m overhang_framework.benchmark.rescore) once they do")
    return {"agent": agent or s["agent"], "split": s["split"], "score": s["score"], "ci_low": s["ci_low"],
            "ci_high": s["ci_high"], "stood": s["stood"], "reward": s["reward"], "area": s.get("area"),
            "n_tasks": s["n_scored"], "seeds": s["seeds"], "budget_kind": s.get("budget_kind"),
            "calls_per_decision": s.get("calls_per_decision"), "seconds_per_decision": s.get("seconds_per_decision"),
            "wall_seconds": None if wall is None else round(float(wall), 1), "jobs": jobs,
            "curve": json.dumps(s["curve"]) if s.get("curve") else "", "physics": s.get("physics"),
            "command": command_of(run_dir), "config": json.dumps(s.get("config", {}), sort_keys=True), "version": __version__, "commit": commit(),
            "date": _dt.date.today().isoformat()}


def check_split(split: Optional[str]) -> None:
    """Refuse a split the leaderboard cannot hold, naming those it can."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; splits: {', '.join(SPLITS)}")


def load(path: Path | str | None = None):
    import pandas as pd

    path = Path(DATA_FILE if path is None else path)
    if not path.exists():
        return pd.DataFrame(columns=list(COLUMNS))
    return pd.read_csv(path, keep_default_na=False)


def add(rows: Sequence[dict], path: Path | str | None = None) -> None:
    """Put ``rows`` into the leaderboard, replacing rows of the same agent, split and kind (with a budget ladder
    or without); sorted by split, score."""
    import pandas as pd

    from overhang_framework.results import atomic_write_text

    path = Path(DATA_FILE if path is None else path)
    board = load(path)
    keys = {(r["agent"], r["split"], bool(r.get("curve"))) for r in rows}
    board = board[[(a, s, bool(c)) not in keys for a, s, c in zip(board["agent"], board["split"], board["curve"])]] \
        if len(board) else board
    board = pd.concat([board, pd.DataFrame(rows, columns=list(COLUMNS))], ignore_index=True)
    board["score"] = board["score"].astype(float)
    order = {s: k for k, s in enumerate(SPLITS)}
    board = board.sort_values(by=["split", "score", "agent"], key=lambda c: c.map(order) if c.name == "split"
                              else (-c if c.name == "score" else c)).reset_index(drop=True)
    atomic_write_text(path, board.to_csv(index=False, float_format="%.6g"))


def markdown(board, split: Optional[str] = None) -> str:
    """The leaderboard as a Markdown table (one split, or all)."""
    lines = ["| agent | split | score [95% CI] | stood | reward | area | calls / decision | s / decision | wall (jobs) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for _, r in board.iterrows():
        if split and r["split"] != split:
            continue
        area = f"{float(r['area']):.3f}" if str(r["area"]) not in ("", "nan", "None") else ""
        calls = f"{float(r['calls_per_decision']):.1f}" if str(r["calls_per_decision"]) not in ("", "nan", "None") else ""
        secs = f"{float(r['seconds_per_decision']):.3f}" if str(r["seconds_per_decision"]) not in ("", "nan", "None") else ""
        wall = ""
        if str(r.get("wall_seconds", "")) not in ("", "nan", "None"):
            minutes = float(r["wall_seconds"]) / 60
            wall = f"{minutes:.1f} min" + (f" ({int(float(r['jobs']))})" if str(r.get("jobs", "")) not in ("", "nan", "None")
                                          else "")
        agent = r["agent"]
        if r["curve"]:
            budgets = [b for b, _ in json.loads(r["curve"])]
            agent += f" (ladder {budgets[0]:g}-{budgets[-1]:g} {r['budget_kind']}; score at the top rung)"
        lines.append(f"| {agent} | {r['split']} | {float(r['score']):.3f} [{float(r['ci_low']):.3f}, "
                     f"{float(r['ci_high']):.3f}] | {100 * float(r['stood']):.0f}% | {float(r['reward']):.3f} | {area} | "
                     f"{calls} | {secs} | {wall} |")
    return "\n".join(lines)


def figure(board, out: Path, split: str = "test") -> None:
    """Score against predictor calls per decision for every row of ``split`` (curves for ladders, one point
    otherwise), and mean raw reward beside it, with the paper's people and the simulated participants."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from overhang_framework.benchmark.figures import _people
    from overhang_framework.results import atomic_output

    rows = board[board["split"] == split]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for k, (_, r) in enumerate(rows.iterrows()):
        colour = plt.cm.tab20(k % 20)
        shape = "sDv^P"[(k // 20) % 5]  # a colour that comes round again comes with another marker
        counted = str(r["calls_per_decision"]) not in ("", "nan", "None")
        # an agent that counts no predictor calls (a program, random placements) sits at the left edge
        x = max(float(r["calls_per_decision"]), NO_CALLS) if counted else NO_CALLS
        if r["curve"]:
            curve = json.loads(r["curve"])
            axes[0].plot([b for b, _ in curve], [s for _, s in curve], marker="o", color=colour, label=r["agent"])
            axes[1].plot([curve[-1][0]], [float(r["reward"])], marker="o", color=colour, ls="none")
        else:
            axes[0].errorbar([x], [float(r["score"])],
                             yerr=[[float(r["score"]) - float(r["ci_low"])], [float(r["ci_high"]) - float(r["score"])]],
                             marker=shape, color=colour, capsize=3, label=r["agent"], ls="none")
            axes[1].plot([x], [float(r["reward"])], marker=shape, color=colour, ls="none")
    for ax, title in ((axes[0], f"score (reward / optimum) on {split}"), (axes[1], f"mean raw reward on {split}")):
        ax.set_xscale("log")
        ax.set_xlabel(f"predictor calls per decision (spent, or the ladder's budget; {NO_CALLS:g}: counts none)")
        ax.set_ylim(bottom=0)
        ax.set_title(title, fontsize=10)
    _people(axes[1], raw=True)
    _people(axes[0], raw=False)
    axes[0].axhline(1.0, color="grey", lw=0.8)
    axes[0].set_ylim(0, 1.05)
    axes[1].legend(fontsize=6, loc="lower right")
    # the agents' legend below both panels: inside one, a table of 30 rows hides half its points
    handles, labels = axes[0].get_legend_handles_labels()
    ncol = 4
    below = 0.15 + 0.13 * -(-len(labels) // ncol)  # inches: a line of 6-point text and its spacing each
    fig.set_figheight(5 + below)
    fig.legend(handles, labels, fontsize=6, loc="lower center", ncol=ncol, frameon=False)
    fig.tight_layout(rect=(0, below / (5 + below), 1, 1))
    with atomic_output(out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
