"""The benchmark's figures: one run's score against compute, and the leaderboard's, with people.

People are drawn on the raw-reward panel, where the paper reports them: the paper's participants'
mean terminal reward, 0.913 with 5 s per placement and 0.979 without (SEM 0.03), measured on the
paper's own 20 tasks, which it does not list; and the framework's simulated participants on ``paper20``
(:data:`SIMULATED`, from ``python -m overhang_framework.benchmark.people``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

#: The paper's participants (Table 2): mean terminal reward and SEM, on the paper's own 20 tasks.
PAPER_PEOPLE = {"5 s per placement": (0.913, 0.03), "no time limit": (0.979, 0.03)}
SIMULATED = Path(__file__).resolve().parent.parent / "data" / "benchmark_people.json"


def simulated_people(path: Optional[Path] = None) -> list[dict]:
    """The simulated participants' rows kept by ``python -m overhang_framework.benchmark.people`` (none if absent)."""
    path = SIMULATED if path is None else Path(path)
    if not path.exists():
        return []
    return json.loads(path.read_text()).get("rows", [])


def _people(ax, raw: bool) -> None:
    """People as horizontal lines with their labels in the panel's legend (drawn by the caller)."""
    if raw:
        for (name, (mean, sem)), colour in zip(PAPER_PEOPLE.items(), ("#c0392b", "#8e44ad")):
            ax.axhline(mean, color=colour, ls="--", lw=1,
                       label=f"paper's people, {name}: {mean:.3f} (paper's own tasks)")
            ax.axhspan(mean - sem, mean + sem, color=colour, alpha=0.08)
    for values, colour in zip(_merged(simulated_people(), "reward" if raw else "score"), ("#16a085", "#2980b9")):
        level = sum(v for _, v in values) / len(values)
        ax.axhline(level, color=colour, ls=":", lw=1.2, label="simulated participants, " + " and ".join(
            f"{condition}: {value:.3f}" for condition, value in values) + " (paper20)")


def _merged(rows: list[dict], key: str, apart: float = 0.01) -> list[list[tuple[str, float]]]:
    """The simulated conditions' ``key`` values, those closer than ``apart`` (relative) to the one before
    them in one group, so that lines which would lie on top of each other are drawn, and labelled, once."""
    groups: list[list[tuple[str, float]]] = []
    for row in sorted(rows, key=lambda r: float(r[key])):
        value = float(row[key])
        if groups and abs(value - groups[-1][-1][1]) <= apart * max(abs(value), 1e-9):
            groups[-1].append((row["condition"], value))
        else:
            groups.append([(row["condition"], value)])
    return groups


def run_figure(result: dict, path: Path) -> None:
    """Score and mean raw reward against the budget (one point without a ladder), people marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from overhang_framework.results import atomic_output

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    if result.get("budgets"):
        budgets = sorted(result["budgets"], key=float)
        xs = [float(b) for b in budgets]
        rungs = [result["budgets"][b] for b in budgets]
        xlabel = "predictor calls per decision" if result.get("budget_kind") == "calls" else "seconds per decision"
    else:
        spent = result.get("calls_per_decision")
        xs = [spent if spent else result.get("seconds_per_decision") or 1.0]
        rungs = [result]
        xlabel = "predictor calls per decision (spent)" if spent else "seconds per decision (spent)"
    for ax, key, title in ((axes[0], "score", "score (reward / optimum)"), (axes[1], "reward", "mean raw reward")):
        ys = [r[key] for r in rungs]
        if key == "score":
            err = [[r["score"] - r["ci_low"] for r in rungs], [r["ci_high"] - r["score"] for r in rungs]]
            ax.errorbar(xs, ys, yerr=err, marker="o", capsize=3, label=result["agent"])
            ax.set_ylim(0, 1.05)
            ax.axhline(1.0, color="grey", lw=0.8)
        else:
            ax.plot(xs, ys, marker="o", label=result["agent"])
        _people(ax, raw=key == "reward")
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_title(title, fontsize=10)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[1].legend(fontsize=7, loc="lower right")
    axes[1].set_ylim(bottom=0)
    area = f", area {result['area']:.3f}" if result.get("area") is not None else ""
    fig.suptitle(f"{result['agent']} on {result['split']}: {result['score']:.3f} "
                 f"[{result['ci_low']:.3f}, {result['ci_high']:.3f}]{area}", fontsize=10)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
