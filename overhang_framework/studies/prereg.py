"""The graded study's preregistration, written by the design (``python -m overhang_framework.study graded_budgets``):
``preregistration.md``, after the OSF template: the hypotheses with their directions, the levels, the sample size
from the design's power analysis and across a range of effect sizes, the exclusion rules, the analysis plan with its
exact command, and what it was written from (the commit, the design's settings hash, the seeds).

The levels between the paper's two conditions (2.5 s and 10 s) rest on a hypothesis (people there lie between the
paper's people), so the power is given for effects of :data:`EFFECT_SCALES` times the designed one: each level's mean
moved toward the mean of the levels' means by that factor, each participant keeping their distance from their
level's mean.
"""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.studies import graded

#: The effects the power is given at, as shares of the designed one.
EFFECT_SCALES = (0.5, 0.75, 1.0)


def scaled(df: pd.DataFrame, levels: Sequence[str], column: str, scale: float) -> pd.DataFrame:
    """``df`` with the differences between the levels' means of ``column`` times ``scale``: each participant's value
    moved by ``(scale - 1)`` times their level's mean minus the mean of the levels' means."""
    out = df.copy()
    at = out["condition"].isin(levels) & np.isfinite(pd.to_numeric(out[column], errors="coerce"))
    means = out[at].groupby("condition")[column].mean()
    centre = float(means.mean())
    shift = out["condition"].map((means - centre) * (scale - 1.0)).fillna(0.0)
    out.loc[at, column] = out.loc[at, column] + shift[at]
    return out


def effect_power(df: pd.DataFrame, levels: Sequence[str], per_level: int, resamples: int, seed: int = 0,
                 scales: Sequence[float] = EFFECT_SCALES) -> pd.DataFrame:
    """For each expected trend and each of ``scales``: the share of ``resamples`` studies of ``per_level`` a level,
    redrawn from ``df`` with the effect scaled, in which the trend holds."""
    rows = []
    for measure in graded.MEASURES:
        if not measure.direction or measure.column not in df.columns or not df[measure.column].notna().any():
            continue
        for scale in scales:
            table = graded.power(scaled(df, levels, measure.column, scale), levels, [measure], sizes=(per_level,),
                                 resamples=resamples, seed=seed)
            rows.append({"measure": measure.name, "effect": float(scale), "per_level": int(per_level),
                         "power": float(table["power"].iloc[0]) if len(table) else math.nan,
                         "resamples": int(resamples)})
    return pd.DataFrame(rows, columns=["measure", "effect", "per_level", "power", "resamples"])


def planned_size(power_table: pd.DataFrame) -> tuple[Optional[int], Optional[str]]:
    """The participants a level the study plans: the largest of the sizes the expected behavioural trends (overhang,
    Γ, lateral reach) need for 80% power, so that each has it; None when one of them has it at no size of the grid.
    Also the measure that sets it."""
    sizes = graded.sample_sizes(power_table)
    primary = [m.name for m in graded.MEASURES if m.direction and m.column in ("avg_overhang", "gamma", "abs_x_late")]
    needed = {m: sizes.get(m) for m in primary if m in sizes}
    if not needed or any(v is None for v in needed.values()):
        return None, next((m for m, v in needed.items() if v is None), None)
    which = max(needed, key=needed.get)
    return needed[which], which


#: Minutes of a session besides the main trials' decisions (the consent, the instructions, the practice, watching
#: each tower's outcome): the paper's sessions took about 20 minutes, of which its people's decisions took about 8
#: (2.47 s and 7.27 s a placement, 43 and 38 people, up to 100 placements each).
OVERHEAD_MINUTES = 12.0


def durations(log: pd.DataFrame, levels: Sequence[str], overhead_minutes: float = OVERHEAD_MINUTES) -> dict[str, float]:
    """Each level's expected duration in minutes: its participants' mean total decision time over the main trials,
    plus ``overhead_minutes`` for the rest of a session."""
    totals = log.groupby(["condition", "participant"])["decision_time"].sum() / 60.0
    return {lv: float(totals.loc[lv].mean()) + overhead_minutes for lv in levels if lv in totals.index}


def consent_minutes(minutes: float) -> int:
    """A duration as the consent page states it: rounded up to 5 minutes."""
    return int(5 * math.ceil(minutes / 5 - 1e-9))


def settings_hash(config: Mapping[str, Any]) -> str:
    """The SHA-256 of the design's settings (the simulated cohort's composed config), as canonical JSON."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def document(levels: Sequence[str], limits: Mapping[str, Optional[float]], power_table: pd.DataFrame,
             effects: pd.DataFrame, minutes: Mapping[str, float], pool: Mapping[str, int], fitted: bool,
             provenance: Mapping[str, Any], command: str, screen: "pd.DataFrame | str | None" = None) -> str:
    """``preregistration.md``: every number it states comes from the arguments, which the design computed.
    ``screen``: the design's participants' practice (:func:`overhang_framework.studies.screenout.simulate_practice`),
    or why it could not be simulated."""
    from overhang_framework.studies import screenout

    label = {m.name: m.label for m in graded.MEASURES}
    n, sets = planned_size(power_table)
    sizes = graded.sample_sizes(power_table)
    grid = sorted(int(v) for v in power_table["per_level"].unique()) if len(power_table) else []
    lines = ["# Preregistration: the graded-budget study", "",
             f"Written by `{command}` from commit `{provenance.get('commit') or 'none (not a git checkout)'}` "
             f"(overhang-framework {provenance.get('version')}), design settings hash `{provenance['settings_hash']}`, "
             f"seed {provenance['seed']}, {provenance['resamples']:,} redrawn studies a power figure. Its figures come "
             "from the simulated participants of the design (`sim/`, `participants.csv`, `power.csv`, "
             "`preregistration_effects.csv`).", "",
             "## Hypotheses", "",
             "Each participant does the task under one time limit per placement (between subjects). With more time "
             "allowed per placement:", ""]
    for m in graded.MEASURES:
        if m.column not in ("avg_overhang", "stable_pct", "gamma", "abs_x_late", "fitted_depth", "fitted_risk",
                            "fitted_K"):
            continue
        if m.column.startswith("fitted_") and not fitted:
            continue
        if m.direction == 0:
            lines.append(f"- **{label[m.name]}**: no trend (tested two-sided; not a hypothesis of the study).")
        else:
            way = "grows" if m.direction > 0 else "falls"
            kind = "secondary (from the fitted models)" if m.column.startswith("fitted_") else "primary"
            lines.append(f"- **H-{m.name}** ({kind}): the {label[m.name]} {way} (Spearman's ρ between a participant's "
                         f"value and their level's rank {'>' if m.direction > 0 else '<'} 0).")
    lines += ["", "## Design", "", "| level | time limit per placement | expected duration |", "|---|---|---|"]
    for lv in levels:
        limit = "none" if limits[lv] is None else f"{limits[lv]:g} s"
        lines.append(f"| `{lv}` | {limit} | about {minutes[lv]:.0f} min |" if lv in minutes else f"| `{lv}` | {limit} | |")
    lines += ["", "(expected duration: the simulated participants' mean total decision time over the main trials, "
              f"plus {OVERHEAD_MINUTES:g} minutes for the rest of a session: the paper's sessions took about 20 "
              "minutes, of which its people's decisions took about 8. Each level's consent page states its duration, "
              "rounded up to 5 minutes: served with `study=graded_budgets`, "
              f"`'durations={{{', '.join(f'{lv}: {consent_minutes(minutes[lv])}' for lv in levels if lv in minutes)}}}'`.)",
              "",
              "Levels are assigned at random, balanced over the participants the server has taken. The 2.5 s and 10 s "
              "levels rest on a hypothesis: their people are assumed to lie between the paper's two conditions.", "",
              "## Sample size", ""]
    if n is not None:
        lines.append(f"**{n} participants per level** ({n * len(levels)} in all, after exclusions): the largest of the "
                     f"sizes the primary hypotheses need for 80% power in the design ({', '.join(f'{label[m]} {sizes[m]}' for m in ('overhang', 'gamma', 'lateral') if sizes.get(m))}; "
                     f"set by the {label[sets]}), from a grid of {', '.join(map(str, grid))} a level.")
        if grid and n == grid[0]:
            lines.append("The grid's smallest size already has the power, so the planned size is the grid's floor, "
                         "not the least the design needs.")
    else:
        lines.append("**No size of the grid gives every primary hypothesis 80% power**"
                     + (f" (the {label[sets]} has it at no size up to {grid[-1]} a level)" if sets and grid else "")
                     + ": the design cannot plan a sample size for them.")
    if isinstance(screen, pd.DataFrame) and len(screen):
        rows = screenout.summary(screen, levels, n)
        lines += ["", "The practice screens out participants before the main trials (below, \"Exclusions\"). The "
                  "design's simulated participants did the served study's practice as its server scores it"
                  + (f"; for {n} a level to remain (in expectation) a level needs:" if n is not None else ":"), "",
                  "| level | screened out in the practice (simulated) | recruits for the planned size |",
                  "|---|---|---|"]
        for r in rows:
            recruit = "–" if n is None else (
                "no number: every simulated participant was screened out" if r["recruit"] is None else str(r["recruit"]))
            lines.append(f"| `{r['level']}` | {r['screened_out']} of {r['simulated']} ({r['share']:.0%}) | {recruit} |")
        if n is not None and rows and all(r["recruit"] is not None for r in rows):
            most = max(r["recruit"] for r in rows)
            lines += ["", f"**Recruit {most} a level, {most * len(levels)} in all.** The server balances the levels "
                      "over everyone it takes, the screened-out included, so every level gets as many recruits as the "
                      "level that screens out most needs. A level's screen-out that differs from these changes who "
                      "remains: the report gives each level's count."]
    elif isinstance(screen, str):
        lines += ["", f"The expected screen-out in the practice could not be simulated ({screen}); the size above is "
                  "after exclusions: recruit more by the screen-out a pilot through the server measures "
                  "(`python -m overhang_framework.experiment pilot`)."]
    if len(effects):
        scales = sorted(effects["effect"].unique())
        lines += ["", f"Power at {int(effects['per_level'].iloc[0])} a level if the effect is smaller than designed "
                  "(each level's mean moved toward the levels' mean; 1 is the designed effect):", "",
                  "| hypothesis | " + " | ".join(f"{s:g} × effect" for s in scales) + " |",
                  "|---|" + "---|" * len(scales)]
        for measure, at in effects.groupby("measure", sort=False):
            by = dict(zip(at["effect"], at["power"]))
            lines.append(f"| {label[measure]} | " + " | ".join(f"{by[s]:.2f}" for s in scales) + " |")
    lines += ["", "## Exclusions", "",
              "A participant who does not pass the practice within the study's attempts is screened out before the "
              "main trials, paid for their time and not analysed (the export leaves them out). Participants who "
              "withdraw are deleted. No other exclusion." + (
                  " The expected screen-out, from the design's simulated participants, is in the recruitment above."
                  if isinstance(screen, pd.DataFrame) and len(screen) else ""), "",
              "## Analysis plan", "",
              "After the last participant, the study's data are exported and analysed by the command that computed "
              "this design's figures:", "", "```bash",
              "python -m overhang_framework.experiment export --out export.jsonl",
              "python -m overhang_framework.study graded_budgets --log export.jsonl --out analysis", "```", "",
              "Each hypothesis is tested by Spearman's ρ between a participant's value and their level's rank, its "
              f"two-sided p from {graded.PERMUTATIONS:,} permutations of the levels over the participants; it holds "
              f"when p < {graded.ALPHA} and ρ goes the hypothesised way. Each level's mean is given with a 95% "
              "percentile bootstrap interval. The fitted measures come from one model fitted to every participant "
              "(its grid includes the neutral value). A study with fewer participants a level than planned says so "
              "in its report's first sentence and concludes nothing.", "",
              "## Simulated participants behind these figures", "",
              ", ".join(f"`{lv}`: {pool.get(lv, 0)}" for lv in levels) + ".", ""]
    return "\n".join(lines)
