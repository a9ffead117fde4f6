"""Table 1 of the paper: overall performance by group, mean ± SEM across participants, permutation tests.

Per participant:

* **total reward**: the sum of the rewards of their trials (the reward is on each trial's last record);
  it grows with the number of tasks, so the table states that number beside the paper's 20;
* **reward per trial**: the mean reward of their trials (the total divided by the trials they did): the
  figure that compares a log of any number of tasks with the paper, whose equivalent is its total / 20
  (the 0.913 and 0.979 of the paper's Table 2);
* **stable proportion** (%): the share of their trials in which the tower stood after every placement
  and that did not end on a timeout;
* **average overhang**: the mean reward over those successful trials (none: the participant is left out);
* **decision time** (s): the mean ``decision_time`` over their records, timeouts included.

Across the participants of a group: mean ± SEM. Two groups are compared per metric with
:func:`~overhang_framework.behaviour.analysis.permutation_p` (participants as units), and the section
opens with what that finds, metric by metric, against the paper.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.shared import (Section, finding, fmt_ms, fmt_p, is_paper_comparison,
                                                 markdown_table, mean_sem, paper_pair, permutation_p, write_csv)
from overhang_framework.behaviour.log import in_step_order, last_records

#: The number of tasks (trials per participant) of the paper's study.
PAPER_TASKS = 20
#: (column, label, digits)
METRICS = (("total_reward", "Total reward", 2), ("reward_per_trial", "Reward per trial", 3),
           ("stable_pct", "Stable proportion (%)", 1), ("avg_overhang", "Average overhang", 3),
           ("decision_time", "Decision time (s)", 2))
#: The metrics the finding speaks of: every one but the total, which depends on the number of tasks.
FINDING = ("reward_per_trial", "stable_pct", "avg_overhang", "decision_time")
#: The paper's Table 1: metric -> (5 s mean, sem, none mean, sem, p as printed). Reward per trial is the
#: total / 20 (every participant did the 20 tasks, so its test is the total's).
PAPER = {"total_reward": (18.25, 0.57, 19.57, 0.56, ".107"),
         "reward_per_trial": (18.25 / PAPER_TASKS, 0.57 / PAPER_TASKS, 19.57 / PAPER_TASKS, 0.56 / PAPER_TASKS,
                              ".107"),
         "stable_pct": (70.2, 2.5, 67.8, 2.1, ".482"),
         "avg_overhang": (1.321, 0.023, 1.460, 0.029, "<.001"), "decision_time": (2.47, 0.07, 7.27, 0.88, "<.001")}
#: Digits of the paper's values where they differ from ours: its total / 20 is exact with four.
PAPER_DIGITS = {"reward_per_trial": 4}
_UNITS = {"stable_pct": "%", "decision_time": " s"}


def trial_outcomes(df: pd.DataFrame) -> pd.DataFrame:
    """One row per trial: ``participant``, ``group``, ``task_id``, ``reward``, ``stood`` (every placement stood,
    no timeout) and ``placed_all`` (the trial reached its last block); the same for any order of ``df``'s rows."""
    df = in_step_order(df)
    last = last_records(df)
    stood_all = df.groupby(["participant", "trial"], sort=False)["stable"].agg(
        lambda s: bool(s.fillna(False).all()))
    out = last[["participant", "group", "task_id", "trial", "reward", "timed_out", "step", "sequence"]].copy()
    out["stood"] = [bool(stood_all[(p, t)]) and not to for p, t, to in
                    zip(out["participant"], out["trial"], out["timed_out"])]
    out["placed_all"] = (out["step"] == out["sequence"].map(len) - 1) & ~out["timed_out"]
    return out.drop(columns=["step", "sequence"]).reset_index(drop=True)


def per_participant(df: pd.DataFrame) -> pd.DataFrame:
    """One row per participant: ``group``, ``participant``, ``trials`` and the metrics of :data:`METRICS`."""
    df = in_step_order(df)
    trials = trial_outcomes(df)
    rows = []
    for (group, participant), t in trials.groupby(["group", "participant"], sort=False):
        ok = t[t["stood"]]
        rows.append({"group": group, "participant": participant, "trials": len(t),
                     "total_reward": float(t["reward"].sum()), "reward_per_trial": float(t["reward"].mean()),
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


def tasks_done(people: pd.DataFrame) -> str:
    """How many tasks the participants did: ``5``, or ``3–5`` when they differ."""
    low, high = int(people["trials"].min()), int(people["trials"].max())
    return str(low) if low == high else f"{low}–{high}"


def markdown(tab: pd.DataFrame, order: Sequence[str], compare, n_resamples: int, tasks: str = "") -> str:
    header = ["Metric"] + [f"{g} (n = {int(tab[(tab.group == g)].n.max())})" for g in order]
    if compare:
        header.append(f"p ({compare[0]} vs {compare[1]})")
    header += ["paper: 5 s", "paper: none", "paper p"]
    rows = []
    for col, label, digits in METRICS:
        sub = tab[tab.metric == col].set_index("group")
        if col == "total_reward" and tasks:
            label = f"{label} (sum over {tasks} tasks; paper: {PAPER_TASKS})"
        elif col == "reward_per_trial":
            label = f"{label} (paper: total / {PAPER_TASKS})"
        row = [label] + [fmt_ms(sub.loc[g, "mean"], sub.loc[g, "sem"], digits) for g in order]
        if compare:
            row.append(fmt_p(sub.loc[compare[0], "p"]))
        pm, d = PAPER[col], PAPER_DIGITS.get(col, digits)
        row += [f"{pm[0]:.{d}f} ± {pm[1]:.{d}f}", f"{pm[2]:.{d}f} ± {pm[3]:.{d}f}", pm[4]]
        rows.append(row)
    note = (f"Mean ± SEM across participants. p: permutation test (independent samples, difference of means, "
            f"two-sided, participants as units, {n_resamples} resamples). Paper: time-constrained (5 s, n = 43) "
            f"and unconstrained (none, n = 38), {PAPER_TASKS} tasks each.")
    return markdown_table(header, rows) + "\n\n" + note


def findings(tab: pd.DataFrame, compare: Optional[Sequence[str]]) -> str:
    """The section's opening: per metric of :data:`FINDING`, the direction, its p and whether it matches the paper."""
    if not compare:
        return ("**Finding:** no two groups compared (give `--compare A B`), so no direction to state; the paper "
                "compares its time-constrained and unconstrained participants.")
    lines, verdicts = [], []
    for col, label, digits in METRICS:
        if col not in FINDING:
            continue
        sub = tab[tab.metric == col].set_index("group")
        pm = PAPER[col]
        pair = paper_pair(compare, pm[0], pm[2])
        unit = _UNITS.get(col, "")
        found = finding(label.split(" (")[0].lower(), compare,
                        (float(sub.loc[compare[0], "mean"]), float(sub.loc[compare[1], "mean"])),
                        float(sub.loc[compare[0], "p"]), None if pair is None else (*pair, pm[4]),
                        lambda v, d=digits, u=unit: f"{v:.{d}f}{u}",
                        show_paper=lambda v, d=PAPER_DIGITS.get(col, digits), u=unit: f"{v:.{d}f}{u}")
        verdicts.append(found.matches)
        lines.append(f"- {found.text}.")
    head = f"**Finding** ({compare[1]} against {compare[0]}; credible: permutation p < .05"
    if is_paper_comparison(compare):
        judged = [v for v in verdicts if v is not None]
        head += f"; {sum(judged)} of {len(judged)} match the paper's verdict"
    return head + "):\n\n" + "\n".join(lines)


def section(df: pd.DataFrame, out: Path, order, compare, settings) -> Section:
    people = per_participant(df)
    tab = table(people, order, compare, settings.n_resamples, settings.seed)
    write_csv(tab, out / "table1.csv")
    write_csv(people, out / "table1_participants.csv")
    text = (findings(tab, compare) + "\n\n" +
            markdown(tab, order, compare, settings.n_resamples, tasks_done(people)) +
            "\n\nRules: total reward is the sum over a participant's trials, so it grows with the number of tasks "
            f"(the paper's: {PAPER_TASKS}); reward per trial is its mean over the trials they did, the figure to set "
            f"beside the paper's (its total / {PAPER_TASKS}); a trial is *stable* when the tower stood "
            "after every placement and it did not end on a timeout; average overhang is the mean reward over a "
            "participant's stable trials (participants without one are left out of that row); decision time is the "
            "mean over a participant's records, timeouts included.")
    return Section("Table 1: overall performance", text, ["table1.csv", "table1_participants.csv"])
