"""Table 1 of the paper: overall performance by group, mean ± SEM across participants, permutation tests.

Per participant:

* **total reward**: the sum of the rewards of their trials (the reward is on each trial's last record);
* **stable proportion** (%): the share of their trials in which the tower stood after every placement
  and that did not end on a timeout;
* **average overhang**: the mean reward over those successful trials (none: the participant is left out);
* **decision time** (s): the mean ``decision_time`` over their records, timeouts included.

Across the participants of a group: mean ± SEM. Two groups are compared per metric with
:func:`~overhang_framework.behaviour.analysis.permutation_p` (participants as units).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.analysis import (Section, fmt_ms, fmt_p, markdown_table, mean_sem, permutation_p,
                                                   write_csv)

#: (column, label, digits)
METRICS = (("total_reward", "Total reward", 2), ("stable_pct", "Stable proportion (%)", 1),
           ("avg_overhang", "Average overhang", 3), ("decision_time", "Decision time (s)", 2))
#: The paper's Table 1: metric -> (5 s mean, sem, none mean, sem, p as printed).
PAPER = {"total_reward": (18.25, 0.57, 19.57, 0.56, ".107"), "stable_pct": (70.2, 2.5, 67.8, 2.1, ".482"),
         "avg_overhang": (1.321, 0.023, 1.460, 0.029, "<.001"), "decision_time": (2.47, 0.07, 7.27, 0.88, "<.001")}


def trial_outcomes(df: pd.DataFrame) -> pd.DataFrame:
    """One row per trial: ``participant``, ``group``, ``task_id``, ``reward``, ``stood`` (every placement stood,
    no timeout) and ``placed_all`` (the trial reached its last block)."""
    last = df.groupby(["participant", "trial"], sort=False).tail(1)
    stood_all = df.groupby(["participant", "trial"], sort=False)["stable"].agg(
        lambda s: bool(s.fillna(False).all()))
    out = last[["participant", "group", "task_id", "trial", "reward", "timed_out", "step", "sequence"]].copy()
    out["stood"] = [bool(stood_all[(p, t)]) and not to for p, t, to in
                    zip(out["participant"], out["trial"], out["timed_out"])]
    out["placed_all"] = (out["step"] == out["sequence"].map(len) - 1) & ~out["timed_out"]
    return out.drop(columns=["step", "sequence"]).reset_index(drop=True)


def per_participant(df: pd.DataFrame) -> pd.DataFrame:
    """One row per participant: ``group``, ``participant``, ``trials`` and the four metrics."""
    trials = trial_outcomes(df)
    rows = []
    for (group, participant), t in trials.groupby(["group", "participant"], sort=False):
        ok = t[t["stood"]]
        rows.append({"group": group, "participant": participant, "trials": len(t),
                     "total_reward": float(t["reward"].sum()),
                     "stable_pct": 100.0 * len(ok) / len(t),
                     "avg_overhang": float(ok["reward"].mean()) if len(ok) else np.nan,
                     "decision_time": float(df.loc[df["participant"] == participant, "decision_time"].mean())})
    return pd.DataFrame(rows)


def table(people: pd.DataFrame, order: Sequence[str], compare: Optional[Sequence[str]], n_resamples: int,
          seed: int) -> pd.DataFrame:
    """Long table: one row per (metric, group) with n, mean, sem; and per metric the p of the compared groups."""
    rows = []
    for col, label, _ in METRICS:
        p = np.nan
        if compare:
            a, b = (people.loc[people["group"] == g, col].to_numpy() for g in compare)
            p = permutation_p(a, b, n_resamples, seed)
        for g in order:
            v = people.loc[people["group"] == g, col]
            m, s = mean_sem(v)
            rows.append({"metric": col, "label": label, "group": g, "n": int(v.notna().sum()), "mean": m, "sem": s,
                         "p": p if compare and g in compare else np.nan,
                         "compared": f"{compare[0]} vs {compare[1]}" if compare else "",
                         "n_resamples": n_resamples if compare else np.nan})
    return pd.DataFrame(rows)


def markdown(tab: pd.DataFrame, order: Sequence[str], compare, n_resamples: int) -> str:
    header = ["Metric"] + [f"{g} (n = {int(tab[(tab.group == g)].n.max())})" for g in order]
    if compare:
        header.append(f"p ({compare[0]} vs {compare[1]})")
    header += ["paper: 5 s", "paper: none", "paper p"]
    rows = []
    for col, label, digits in METRICS:
        sub = tab[tab.metric == col].set_index("group")
        row = [label] + [fmt_ms(sub.loc[g, "mean"], sub.loc[g, "sem"], digits) for g in order]
        if compare:
            row.append(fmt_p(sub.loc[compare[0], "p"]))
        pm = PAPER[col]
        row += [f"{pm[0]:.{digits}f} ± {pm[1]:.{digits}f}", f"{pm[2]:.{digits}f} ± {pm[3]:.{digits}f}", pm[4]]
        rows.append(row)
    note = (f"Mean ± SEM across participants. p: permutation test (independent samples, difference of means, "
            f"two-sided, participants as units, {n_resamples} resamples). Paper: time-constrained (5 s, n = 43) "
            "and unconstrained (none, n = 38).")
    return markdown_table(header, rows) + "\n\n" + note


def section(df: pd.DataFrame, out: Path, order, compare, settings) -> Section:
    people = per_participant(df)
    tab = table(people, order, compare, settings.n_resamples, settings.seed)
    write_csv(tab, out / "table1.csv")
    write_csv(people, out / "table1_participants.csv")
    text = (markdown(tab, order, compare, settings.n_resamples) +
            "\n\nRules: total reward is the sum over a participant's trials; a trial is *stable* when the tower stood "
            "after every placement and it did not end on a timeout; average overhang is the mean reward over a "
            "participant's stable trials (participants without one are left out of that row); decision time is the "
            "mean over a participant's records, timeouts included.")
    return Section("Table 1: overall performance", text, ["table1.csv", "table1_participants.csv"])
