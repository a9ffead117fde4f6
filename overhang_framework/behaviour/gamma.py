"""Order dependency Γ of the towers people built (the paper's Fig. 3b).

A trial's final tower is its last record's ``tower_before`` with that record's block added. Only trials
that placed every block of their sequence count (a trial that ended on a collapse or a timeout before
its last block has no final tower); a trial whose last placement toppled the tower counts, with
Γ = 1 (no construction order of a falling tower stands). Γ of each tower comes from
:func:`~overhang_framework.behaviour.order_dependency.order_counts_many` under the world's physics
(one batched physics call for all towers). Γ of a participant is the mean over their towers; Γ of a
task in a group the mean over that group's towers of the task.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.analysis import (Section, colour, fmt_ms, markdown_table, mean_sem,
                                                   p_is, permutation_p, save_figure, write_csv)
from overhang_framework.geometry import Block, Geometry, check_width

PAPER = {"unconstrained": (0.24, 0.03), "time_limited": (0.15, 0.02), "p": ".022"}


def final_towers(df: pd.DataFrame) -> pd.DataFrame:
    """One row per trial that placed every block: ``participant``, ``group``, ``task_id``, ``trial``,
    ``stood`` (the last placement left it standing) and ``tower`` (a :class:`Geometry`, ground block first)."""
    last = df.groupby(["participant", "trial"], sort=False).tail(1)
    last = last[(last["step"] == last["sequence"].map(len) - 1) & ~last["timed_out"]]
    towers = [Geometry(tuple(Block(check_width(w), float(x), int(l)) for w, x, l in before)
                       + (Block(check_width(w), float(x), int(l)),))
              for before, w, x, l in zip(last["tower_before"], last["width"], last["x"], last["layer"])]
    out = last[["participant", "group", "task_id", "trial"]].copy()
    out["stood"] = last["stable"].fillna(False).astype(bool).to_numpy()
    out["tower"] = towers
    return out.reset_index(drop=True)


def tower_gammas(df: pd.DataFrame, world, progress: bool = False) -> pd.DataFrame:
    """:func:`final_towers` with ``valid_orders``, ``stable_orders`` and ``gamma`` (NaN: no valid order)."""
    from overhang_framework.behaviour.order_dependency import order_counts_many

    towers = final_towers(df)
    counts = order_counts_many(list(towers["tower"]), world, show_progress=progress) if len(towers) else []
    towers["valid_orders"] = [c.valid_orders for c in counts]
    towers["stable_orders"] = [c.stable_orders for c in counts]
    towers["gamma"] = [np.nan if c.gamma is None else c.gamma for c in counts]
    return towers


def per_participant(towers: pd.DataFrame) -> pd.DataFrame:
    """Γ of each participant: the mean over their towers (those with a valid order)."""
    return (towers.dropna(subset=["gamma"]).groupby(["group", "participant"], sort=False)
            .agg(gamma=("gamma", "mean"), towers=("gamma", "size")).reset_index())


def per_task(towers: pd.DataFrame) -> pd.DataFrame:
    """Γ of each task in each group: the mean over the group's towers of the task."""
    return (towers.dropna(subset=["gamma"]).groupby(["group", "task_id"], sort=False)
            .agg(gamma=("gamma", "mean"), towers=("gamma", "size")).reset_index())


def figure(people: pd.DataFrame, tasks: pd.DataFrame, order: Sequence[str], p: float, compare):
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
    title = "Order dependency Γ of final towers (dots; black: mean ± SEM)"
    if compare and np.isfinite(p):
        title += f"\n{compare[0]} vs {compare[1]} across participants: permutation {p_is(p)}"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def section(df: pd.DataFrame, out: Path, order, compare, settings, world) -> Section:
    towers = tower_gammas(df, world, settings.progress)
    people = per_participant(towers)
    tasks = per_task(towers)
    p = np.nan
    if compare:
        a, b = (people.loc[people["group"] == g, "gamma"].to_numpy() for g in compare)
        p = permutation_p(a, b, settings.n_resamples, settings.seed)
    rows, summary = [], []
    for g in order:
        t = towers[towers["group"] == g]
        mp, sp = mean_sem(people.loc[people["group"] == g, "gamma"])
        mt, st = mean_sem(tasks.loc[tasks["group"] == g, "gamma"])
        paper = PAPER.get(g)
        summary.append({"group": g, "participants": int((people["group"] == g).sum()), "towers": len(t),
                        "towers_standing": int(t["stood"].sum()), "no_valid_order": int(t["gamma"].isna().sum()),
                        "gamma_participants_mean": mp, "gamma_participants_sem": sp,
                        "gamma_tasks_mean": mt, "gamma_tasks_sem": st,
                        "p": p if compare and g in compare else np.nan,
                        "n_resamples": settings.n_resamples if compare else np.nan})
        rows.append([g, summary[-1]["participants"], f"{len(t)} ({summary[-1]['towers_standing']} standing)",
                     fmt_ms(mp, sp, 3), fmt_ms(mt, st, 3), f"{paper[0]} ± {paper[1]}" if paper else "–"])
    summ = pd.DataFrame(summary)
    write_csv(summ, out / "gamma.csv")
    write_csv(people, out / "gamma_participants.csv")
    write_csv(tasks, out / "gamma_tasks.csv")
    write_csv(towers.assign(tower=[[[b.width, b.x, b.layer] for b in t.blocks] for t in towers["tower"]]),
              out / "gamma_towers.csv")
    files = ["gamma.csv", "gamma_participants.csv", "gamma_tasks.csv", "gamma_towers.csv"]
    text = markdown_table(["group", "participants", "final towers", "Γ across participants", "Γ across tasks",
                           "paper (participants)"], rows)
    if compare:
        text += (f"\n\n{compare[0]} vs {compare[1]} across participants: permutation {p_is(p)} "
                 f"({settings.n_resamples} resamples; paper: p = {PAPER['p']}).")
    text += ("\n\nRules: a trial's final tower is its last record's `tower_before` plus its block; only trials that "
             "placed every block count (one whose last placement toppled the tower has Γ = 1). Γ = 1 − stable "
             "orders / valid orders under the world's physics; a participant's Γ is the mean over their towers, a "
             "task's the mean over the group's towers of it; towers with no valid order are left out.")
    if len(people):
        save_figure(figure(people, tasks, order, p, compare), out / "fig3b_gamma.png")
        files.append("fig3b_gamma.png")
    else:
        text += "\n\nNo trial placed every block: no Γ and no figure."
    return Section("Order dependency Γ (Fig. 3b)", text, files)
