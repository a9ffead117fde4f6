"""Order dependency Γ of the towers people built (the paper's Fig. 3b).

A trial's final tower is its last record's ``tower_before`` with that record's block added (a timeout
places nothing: its ``tower_before``). Which trials count is a setting, ``towers``
(:data:`~overhang_framework.behaviour.analysis.GAMMA_TOWERS`):

* ``completed`` (the default, the paper's "completed tower :math:`G_T`"): trials that placed every
  block of their sequence with the tower standing after each placement, the trials that earn a reward.
  A trial that collapsed, at its last block or earlier, or timed out built no completed tower;
* ``final``: every trial's final tower, however the trial ended: one that fell has no stable order
  under a physics that agrees with the log (Γ = 1), one that timed out counts with the blocks it had.

Γ of each tower comes from :func:`~overhang_framework.behaviour.order_dependency.order_counts_many`
under the world's physics (one batched physics call for the towers of both readings). Γ of a
participant is the mean over their towers; Γ of a task in a group the mean over that group's towers of
the task. The section reports the chosen reading and, in one sentence, the other.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.shared import (GAMMA_TOWERS, Section, colour, finding, fmt_ms, markdown_table,
                                                 mean_sem, p_is, paper_pair, permutation_p, save_figure,
                                                 write_csv)
from overhang_framework.behaviour.log import in_step_order, last_records
from overhang_framework.geometry import Block, Geometry, check_width

PAPER = {"unconstrained": (0.24, 0.03), "time_limited": (0.15, 0.02), "p": ".022"}
#: What each reading counts, for the report.
COUNTS = {"completed": "completed towers: every block placed, the tower standing after each placement",
          "final": "every trial's final tower, however the trial ended"}


def _check(towers: str) -> None:
    if towers not in GAMMA_TOWERS:
        from overhang_framework.errors import OverhangError

        raise OverhangError(f"towers: unknown reading {towers!r}; readings: {', '.join(GAMMA_TOWERS)}")


def trial_towers(df: pd.DataFrame) -> pd.DataFrame:
    """One row per trial, in (participant, trial) order whatever the order of ``df``'s rows: ``participant``,
    ``group``, ``task_id``, ``trial``, ``ended`` (``completed``, ``collapse`` or ``timeout``), ``completed``
    and ``tower`` (its final tower, a :class:`Geometry`, ground block first)."""
    df = in_step_order(df)
    stood = df.groupby(["participant", "trial"], sort=False)["stable"].agg(lambda s: bool(s.fillna(False).all()))
    last = last_records(df)
    towers, ended = [], []
    for p, t, before, w, x, layer, timed_out in zip(last["participant"], last["trial"], last["tower_before"],
                                                    last["width"], last["x"], last["layer"], last["timed_out"]):
        blocks = tuple(Block(check_width(bw), float(bx), int(bl)) for bw, bx, bl in before)
        if timed_out:
            towers.append(Geometry(blocks))
            ended.append("timeout")
        else:
            towers.append(Geometry(blocks + (Block(check_width(w), float(x), int(layer)),)))
            ended.append("completed" if stood[(p, t)] else "collapse")
    out = last[["participant", "group", "task_id", "trial"]].copy()
    out["ended"] = ended
    out["completed"] = out["ended"] == "completed"
    out["tower"] = towers
    return out.reset_index(drop=True)


def final_towers(df: pd.DataFrame, towers: str = "completed") -> pd.DataFrame:
    """The rows of :func:`trial_towers` that Γ counts under the reading ``towers`` (``completed`` or ``final``)."""
    _check(towers)
    rows = trial_towers(df)
    return rows if towers == "final" else rows[rows["completed"]].reset_index(drop=True)


def with_gammas(rows: pd.DataFrame, world, progress: bool = False) -> pd.DataFrame:
    """``rows`` (from :func:`trial_towers`) with ``valid_orders``, ``stable_orders`` and ``gamma`` (NaN: no
    valid order), all towers in one batched physics call."""
    from overhang_framework.behaviour.order_dependency import order_counts_many

    rows = rows.copy()
    counts = order_counts_many(list(rows["tower"]), world, show_progress=progress) if len(rows) else []
    rows["valid_orders"] = [c.valid_orders for c in counts]
    rows["stable_orders"] = [c.stable_orders for c in counts]
    rows["gamma"] = [np.nan if c.gamma is None else c.gamma for c in counts]
    return rows


def tower_gammas(df: pd.DataFrame, world, progress: bool = False, towers: str = "completed") -> pd.DataFrame:
    """:func:`final_towers` of the reading ``towers`` with ``valid_orders``, ``stable_orders`` and ``gamma``."""
    return with_gammas(final_towers(df, towers), world, progress)


def counted(rows: pd.DataFrame, towers: str) -> pd.DataFrame:
    """The rows of :func:`with_gammas` (every trial) that the reading ``towers`` counts."""
    _check(towers)
    return rows if towers == "final" else rows[rows["completed"]]


def per_participant(towers: pd.DataFrame) -> pd.DataFrame:
    """Γ of each participant: the mean over their towers (those with a valid order)."""
    return (towers.dropna(subset=["gamma"]).groupby(["group", "participant"], sort=False)
            .agg(gamma=("gamma", "mean"), towers=("gamma", "size")).reset_index())


def per_task(towers: pd.DataFrame) -> pd.DataFrame:
    """Γ of each task in each group: the mean over the group's towers of the task."""
    return (towers.dropna(subset=["gamma"]).groupby(["group", "task_id"], sort=False)
            .agg(gamma=("gamma", "mean"), towers=("gamma", "size")).reset_index())


def figure(people: pd.DataFrame, tasks: pd.DataFrame, order: Sequence[str], p: float, compare,
           towers: str = "completed"):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(max(7.5, 2.2 * len(order) + 3), 3.8), sharey=True)
    rng = np.random.default_rng(0)
    for ax, data, what in ((axes[0], people, "participants"), (axes[1], tasks, "tasks")):
        for i, g in enumerate(order):
            v = data.loc[data["group"] == g, "gamma"].to_numpy()
            if v.size == 0:
                continue
            c = colour(g, order)
            if v.size > 1:
                parts = ax.violinplot([v], positions=[i], widths=0.8, showextrema=False)
                for body in parts["bodies"]:
                    body.set_facecolor(c)
                    body.set_alpha(0.25)
            ax.scatter(i + rng.uniform(-0.12, 0.12, v.size), v, s=12, color=c, alpha=0.75, zorder=3)
            m, s = mean_sem(v)
            ax.errorbar([i + 0.3], [m], yerr=[0 if not np.isfinite(s) else s], fmt="o", color="black",
                        capsize=4, zorder=4)
            ax.text(i + 0.36, m, f"{m:.2f}", va="center", fontsize=8)
        ax.set_xticks(range(len(order)), [g.replace("_", " ") for g in order], rotation=15 if len(order) > 2 else 0)
        ax.set_title(f"across {what} (n per group: "
                     f"{', '.join(str(int((data['group'] == g).sum())) for g in order)})", fontsize=9)
        ax.set_xlim(-0.6, len(order) - 0.3)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("order dependency Γ")
    title = f"Order dependency Γ of {'completed towers' if towers == 'completed' else 'every trial’s final tower'}" \
            " (dots; black: mean ± SEM)"
    if compare and np.isfinite(p):
        title += f"\n{compare[0]} vs {compare[1]} across participants: permutation {p_is(p)}"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def _stats(rows: pd.DataFrame, reading: str, order, compare, settings):
    """Per reading: the summary rows by group, Γ per participant and per task, and the p across participants."""
    towers = counted(rows, reading)
    people, tasks = per_participant(towers), per_task(towers)
    p = np.nan
    if compare:
        a, b = (people.loc[people["group"] == g, "gamma"].to_numpy() for g in compare)
        p = permutation_p(a, b, settings.n_resamples, settings.seed)
    summary = []
    for g in order:
        t, all_trials = towers[towers["group"] == g], rows[rows["group"] == g]
        mp, sp = mean_sem(people.loc[people["group"] == g, "gamma"])
        mt, st = mean_sem(tasks.loc[tasks["group"] == g, "gamma"])
        summary.append({"reading": reading, "group": g, "participants": int((people["group"] == g).sum()),
                        "trials": len(all_trials), "towers": len(t), "completed": int(t["completed"].sum()),
                        "no_stable_order": int((t["stable_orders"] == 0).sum() - t["gamma"].isna().sum()),
                        "no_valid_order": int(t["gamma"].isna().sum()),
                        "gamma_participants_mean": mp, "gamma_participants_sem": sp,
                        "gamma_tasks_mean": mt, "gamma_tasks_sem": st,
                        "p": p if compare and g in compare else np.nan,
                        "n_resamples": settings.n_resamples if compare else np.nan})
    return pd.DataFrame(summary), people, tasks, p


def _finding(summ: pd.DataFrame, compare, p: float, reading: str, paper: bool):
    rows = summ.set_index("group")
    ours = tuple(float(rows.loc[g, "gamma_participants_mean"]) for g in compare)
    pair = paper_pair(compare, PAPER["time_limited"][0], PAPER["unconstrained"][0]) if paper else None
    return finding("Γ across participants", compare, ours, p, None if pair is None else (*pair, PAPER["p"]),
                   lambda v: f"{v:.3f}", show_paper=lambda v: f"{v:.2f}",
                   no_paper="; the paper's Γ is of completed towers" if reading == "final" else
                   "; the paper compares its time-constrained and unconstrained participants only")


def section(df: pd.DataFrame, out: Path, order, compare, settings, world) -> Section:
    reading = getattr(settings, "gamma_towers", "completed")
    _check(reading)
    other = next(r for r in GAMMA_TOWERS if r != reading)
    rows = with_gammas(trial_towers(df), world, settings.progress)
    summ, people, tasks, p = _stats(rows, reading, order, compare, settings)
    summ_other, _, _, p_other = _stats(rows, other, order, compare, settings)
    both = pd.concat([summ, summ_other], ignore_index=True)
    write_csv(both, out / "gamma.csv")
    write_csv(people, out / "gamma_participants.csv")
    write_csv(tasks, out / "gamma_tasks.csv")
    write_csv(rows.assign(tower=[[[b.width, b.x, b.layer] for b in t.blocks] for t in rows["tower"]]),
              out / "gamma_towers.csv")
    files = ["gamma.csv", "gamma_participants.csv", "gamma_tasks.csv", "gamma_towers.csv"]
    if compare:
        main = _finding(summ, compare, p, reading, paper=reading == "completed")
        alt = _finding(summ_other, compare, p_other, other, paper=other == "completed")
        text = (f"**Finding** (`{reading}`, {COUNTS[reading]}; credible: permutation p < .05): {main.text}. "
                f"Counting `{other}` instead ({COUNTS[other]}; `--gamma-towers {other}`): {alt.text}.")
    else:
        text = ("**Finding:** no two groups compared (give `--compare A B`), so no direction to state; the paper "
                f"finds Γ higher without a time limit ({PAPER['unconstrained'][0]} vs {PAPER['time_limited'][0]}, "
                f"p = {PAPER['p']}).")
    table = []
    for r in both.itertuples():
        paper = PAPER.get(r.group) if r.reading == "completed" else None
        table.append([f"`{r.reading}`" + (" (reported)" if r.reading == reading else ""), r.group, r.participants,
                      f"{r.towers} of {r.trials}" + (f" ({r.no_stable_order} with no stable order here)"
                                                     if r.no_stable_order else ""),
                      fmt_ms(r.gamma_participants_mean, r.gamma_participants_sem, 3),
                      fmt_ms(r.gamma_tasks_mean, r.gamma_tasks_sem, 3),
                      f"{paper[0]} ± {paper[1]}" if paper else "–"])
    text += "\n\n" + markdown_table(["towers", "group", "participants", "towers of trials", "Γ across participants",
                                     "Γ across tasks", "paper (participants)"], table)
    if compare:
        text += (f"\n\n{compare[0]} vs {compare[1]} across participants: permutation {p_is(p)} (`{reading}`), "
                 f"{p_is(p_other)} (`{other}`); {settings.n_resamples} resamples; paper: p = {PAPER['p']}.")
    text += ("\n\nRules: a trial's final tower is its last record's `tower_before` plus its block (a timeout's: "
             "`tower_before`). `completed` counts the trials that placed every block with the tower standing after "
             "each placement (the paper's completed towers); `final` counts every trial's final tower, so a tower "
             "that fell, whenever it fell, has Γ = 1 when the world's physics agrees. Γ = 1 − stable orders / valid "
             "orders under the world's physics; a tower the log saw standing may still have no stable order here "
             "when this physics differs from the one it was built under. A participant's Γ is the mean over their "
             "towers (participants without one are left out), a task's the mean over the group's towers of it; "
             "towers with no valid order are left out.")
    if len(people):
        save_figure(figure(people, tasks, order, p, compare, reading), out / "fig3b_gamma.png")
        files.append("fig3b_gamma.png")
    else:
        text += f"\n\nNo trial counts under `{reading}`: no Γ and no figure."
    return Section("Order dependency Γ (Fig. 3b)", text, files)
