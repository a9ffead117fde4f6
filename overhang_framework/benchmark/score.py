"""The benchmark's metric: reward / optimum per task, a bootstrap interval over tasks, the area under
the score-against-compute curve.

* A task's **normalised** reward is its reward over its proven optimum (the optimum under the same
  physics and resolution, from the optima file). A task scores its mean over seeds.
* The **score** of a split is the mean over tasks; the **95% interval** resamples tasks (10,000
  bootstrap draws, seeded), so it says how much the score would move on another draw of tasks.
* **stood** is the share of episodes whose tower stood to the end; **reward** the mean raw reward.
* With a ladder of budgets, the **curve** is the score at each rung and the **area** is the area
  under it against log budget, over the ladder's range, divided by that range: a trapezoid rule on
  log-spaced points, so each doubling of compute weighs the same and an agent that is good with
  little compute scores more than one that gets there only at the top (as AUCCESS weighs early
  attempts). An agent that takes no budget has one point, at the compute it spent, and no area.

Every function here sorts its rows first, so the answer does not depend on their order.
"""

from __future__ import annotations

import math
import re
from typing import Iterable, Optional, Sequence

import numpy as np

BOOTSTRAP = 10_000
LEVEL = 0.95


def _key(row: dict) -> tuple:
    budget = row.get("budget")
    return (str(row["task_id"]), -1.0 if budget is None or budget == "" else float(budget), int(row["seed"]))


def normalised(reward: float, optimum: Optional[float]) -> float:
    """``reward / optimum`` (NaN when the optimum is unknown)."""
    if optimum is None or not np.isfinite(optimum) or optimum <= 0:
        return float("nan")
    return float(reward) / float(optimum)


def per_task(rows: Iterable[dict]) -> dict[str, float]:
    """Each task's mean normalised reward over its seeds (tasks without an optimum left out)."""
    by_task: dict[str, list] = {}
    for row in sorted(rows, key=_key):
        value = float(row["normalised"]) if row.get("normalised") not in (None, "") else float("nan")
        if np.isfinite(value):
            by_task.setdefault(str(row["task_id"]), []).append(value)
    return {t: float(np.mean(v)) for t, v in sorted(by_task.items())}


def bootstrap_interval(values: Sequence[float], draws: int = BOOTSTRAP, level: float = LEVEL,
                       seed: int = 0) -> tuple[float, float]:
    """The percentile interval of the mean of ``values`` over ``draws`` resamples (seeded)."""
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return float("nan"), float("nan")
    if len(values) == 1:
        return float(values[0]), float(values[0])
    rng = np.random.default_rng(seed)
    means = values[rng.integers(len(values), size=(draws, len(values)))].mean(axis=1)
    alpha = (1 - level) / 2
    return float(np.quantile(means, alpha)), float(np.quantile(means, 1 - alpha))


def summarise(rows: Sequence[dict], draws: int = BOOTSTRAP) -> dict:
    """Score, interval, share stood, mean raw reward, and counts, of the rows of one budget."""
    rows = sorted(rows, key=_key)
    tasks = per_task(rows)
    values = list(tasks.values())
    low, high = bootstrap_interval(values, draws)
    calls = [float(r["calls"]) for r in rows if r.get("calls") not in (None, "")]
    steps = [int(r.get("steps") or 0) for r in rows]
    return {
        "score": float(np.mean(values)) if values else float("nan"), "ci_low": low, "ci_high": high,
        "stood": float(np.mean([bool(r["stood"]) for r in rows])) if rows else float("nan"),
        "reward": float(np.mean([float(r["reward"]) for r in rows])) if rows else float("nan"),
        "n_tasks": len({r["task_id"] for r in rows}), "n_scored": len(values),
        "seeds": len({int(r["seed"]) for r in rows}), "episodes": len(rows),
        "above_optimum": sorted({str(r["task_id"]) for r in rows
                                 if r.get("normalised") not in (None, "") and float(r["normalised"]) > 1 + 1e-9}),
        "calls_per_decision": float(sum(calls) / max(1, sum(steps))) if calls and len(calls) == len(rows) else None,
        "seconds_per_decision": float(sum(float(r["seconds"]) for r in rows) / max(1, sum(steps))) if rows else None,
        "failures": {k: v for k, v in _reasons(rows).items()},
    }


#: Where a reason's particulars (placement, coordinates, exit code, timeout) begin.
_PARTICULARS = re.compile(r" at placement| x=| within | for block|[:(;]")
#: Reasons that are the agent's faults rather than the tower's (see :func:`reason_kind`).
AGENT_FAULTS = ("agent crashed", "agent gave no answer", "agent could not start", "malformed answer",
                "illegal placement")


def reason_kind(reason: str) -> str:
    """The kind of an episode's reason, without its particulars: ``fell``, ``agent crashed``, ``agent gave no
    answer``, ``malformed answer``, ``illegal placement``, ``agent could not start``, ``no legal placement``."""
    reason = str(reason or "")
    if "fell" in reason:
        return "fell"
    return _PARTICULARS.split(reason, maxsplit=1)[0].strip()


def _reasons(rows: Sequence[dict]) -> dict:
    """How many episodes ended for each kind of reason."""
    counts: dict = {}
    for r in rows:
        if r.get("reason"):
            kind = reason_kind(r["reason"])
            counts[kind] = counts.get(kind, 0) + 1
    return dict(sorted(counts.items()))


def area(curve: Sequence[tuple[float, float]]) -> Optional[float]:
    """The area under ``(budget, score)`` points against log budget, divided by the log range
    (trapezoids); ``None`` for fewer than two budgets."""
    points = sorted((float(b), float(s)) for b, s in curve)
    if len(points) < 2 or points[0][0] <= 0:
        return None
    logs = [math.log(b) for b, _ in points]
    total = sum((logs[i + 1] - logs[i]) * (points[i][1] + points[i + 1][1]) / 2 for i in range(len(points) - 1))
    return float(total / (logs[-1] - logs[0]))


def summary(rows: Sequence[dict], draws: int = BOOTSTRAP) -> dict:
    """The whole run's summary: with one budget (or none) the scores themselves; with a ladder, each
    rung's, the curve and its area, and the top rung's figures at the top level."""
    budgets = sorted({None if r.get("budget") in (None, "") else float(r["budget"]) for r in rows},
                     key=lambda b: -1 if b is None else b)
    if len(budgets) <= 1:
        return summarise(rows, draws)
    rungs = {b: summarise([r for r in rows if r.get("budget") not in (None, "") and float(r["budget"]) == b], draws)
             for b in budgets if b is not None}
    top = rungs[max(rungs)]
    curve = [[b, rungs[b]["score"]] for b in sorted(rungs)]
    return {**top, "budgets": {f"{b:g}": s for b, s in rungs.items()}, "curve": curve, "area": area(curve)}
