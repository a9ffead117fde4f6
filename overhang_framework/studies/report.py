"""A study's report (``study.md``): what it found in a sentence a finding, with the direction, the power of its
size, and what was not tested and why."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.studies.findings import ALPHA, MULTIPLES, NULL_KEEPS, TARGET_POWER
from overhang_framework.studies.steps import Steps


def _check_line(path: Path) -> Optional[str]:
    """The predictive check's first finding (check.md's first bullet), or None."""
    if not path.exists():
        return None
    import re

    bullets = [line[2:].strip() for line in path.read_text().splitlines() if line.startswith("- ")]
    return re.sub(r"^\*\*[^*]+:\*\*\s*", "", bullets[0]) if bullets else None


def _size(multiple: Any, sizes: dict[str, int]) -> str:
    if multiple == "n/a":
        return ""
    n = sum(sizes.values())
    if multiple is None:
        return f"more than {int(round(n * MULTIPLES[-1]))}"
    return f"about {int(round(n * multiple))}"


def shortfall(sizes: Mapping[str, int], planned: Mapping[str, int]) -> Optional[str]:
    """The report's first sentence when a condition has fewer participants than the study is designed for (the
    paper's), saying which; None when none has."""
    short = [(c, sizes.get(c, 0), int(n)) for c, n in planned.items() if sizes.get(c, 0) < int(n)]
    if not short:
        return None
    c, have, want = min(short, key=lambda t: t[1] / t[2])
    return (f"**Nothing can be concluded from this study:** it has {have} participant{'s' * (have != 1)} in its "
            f"condition `{c}`, fewer than the {want} the study is designed for (the paper's), at which the findings' "
            "power was planned; a finding it does not show may be there, and one it shows may be chance.")


def report(study: str, table: pd.DataFrame, steps: Steps, sizes: dict[str, int], simulated: dict[str, int],
           n_tasks: Optional[int], resamples: int, planted: bool, depths: Sequence[int], seconds: float,
           bootstrap: bool = False, check_line: Optional[str] = None,
           why: Optional[Mapping[str, str]] = None, people: bool = False,
           planned: Optional[Mapping[str, int]] = None) -> str:
    """``study.md``. ``people``: the participants are people (a log), not simulated, so the findings are the
    paper's, tested on them; ``planned``: the participants a condition the study is designed for, whose shortfall
    the first sentence names (:func:`shortfall`)."""
    from overhang_framework.behaviour.analysis import fmt_p, markdown_table, p_is

    why = why or {}
    n = sum(sizes.values())
    who = "" if people else "simulated "
    shown = table[table["finding"] != "switch"] if not planted else table
    untested = shown[~shown["tested"]] if "tested" in shown.columns else shown.iloc[:0]
    shown = shown.drop(untested.index)
    holds = shown[shown["holds"] & (shown["finding"] != "stable")]
    kind = "planted" if planted else "null"
    expected = "each finding" if planted else \
        "none of the effects of a dual transition (beyond chance), and the approximate physics its cohort keeps"
    said = shortfall(sizes, planned) if planned else None
    if people:
        expected = "each finding of the paper's dual transition"
    lines = [f"# Study: {study}" + (": what people did" if people else f" ({kind})"), "",
             *([said, ""] if said else []),
             f"{n} {'people' if people else 'participants'} ({', '.join(f'{v} {k}' for k, v in sizes.items())}), "
             f"{'all' if n_tasks is None else n_tasks} tasks each, "
             f"{'fitted depths ' + ', '.join(map(str, depths)) if depths else 'no fit'}; "
             f"{'the paper predicts' if people else 'the study should show'} {expected}.", ""]
    names = ", ".join(f"{r.finding}" for r in holds.itertuples()) or "none"
    effects = len(shown[shown["finding"] != "stable"])
    lines.append(f"- **Found:** {len(holds)} of {effects} effects at α = .05 ({names}); the stable proportion "
                 f"{'does not differ' if bool(table.set_index('finding').loc['stable', 'holds']) else 'differs'} "
                 "between the conditions.")
    missed = shown[~shown["holds"] & (shown["finding"] != "stable")]
    if planted and len(missed):
        lines.append("- **Not found:** " + "; ".join(
            f"{r.finding} ({r.text}: {r.statistic}" + (f", {p_is(r.p)}" if np.isfinite(r.p) else "")
            + ")" for r in missed.itertuples()) + ".")
    elif not planted:
        absent = shown[~shown["finding"].isin(NULL_KEEPS)]
        wrong = absent[absent["holds"]]
        lines.append(f"- **As a null study should:** {'yes' if not len(wrong) else 'no'}; "
                     + (f"{len(wrong)} of {len(absent)} effects the null cohort lacks appear at α = .05 "
                        f"({', '.join(wrong['finding'])})." if len(wrong)
                        else f"none of the {len(absent)} effects the null cohort lacks appears at α = .05."))
        kept = shown[shown["finding"].isin(NULL_KEEPS) & (shown["finding"] != "stable")]
        for r in kept.itertuples():
            lines.append(f"- **Kept by the null cohort** (its participants judge with a noisy IPE): {r.text}, "
                         f"{'found' if r.holds else 'not found'} ({r.statistic}"
                         + (f", {p_is(r.p)}" if np.isfinite(r.p) else "") + ")"
                         + (f", in {r.rate:.0%} of redrawn studies" if r.rate is not None and np.isfinite(r.rate) else "")
                         + ".")
    if resamples:
        word = "power" if planted else "false-positive rate"
        rates = "; ".join(f"{r.finding} {r.rate:.0%}" for r in shown.itertuples() if r.rate is not None
                          and r.finding != "stable" and (planted or r.finding not in NULL_KEEPS))
        how = ("with replacement from the study's own participants: a bootstrap, which gives the rate of the "
               "effect this sample happens to show, an optimistic estimate; --pool 2 or more draws them without "
               "replacement from a larger cohort" if bootstrap else "without replacement")
        lines.append(f"- **{word.capitalize()}** ({resamples} studies of {n} redrawn from the {sum(simulated.values())} "
                     f"{who}participants, {how}): {rates}.")
        if planted:
            low = shown[(shown["rate"] < TARGET_POWER) & (shown["finding"] != "stable")]
            if len(low):
                lines.append("- **Below 0.8:** " + "; ".join(
                    f"{r.finding} ({r.rate:.0%} at {n}; {r.size_for_power or 'not redrawn'} participants reach 0.8"
                    + (f"; {why[r.finding]}" if r.finding in why else "") + ")"
                    for r in low.itertuples()) + f". Studies larger than the {who}cohort are drawn with "
                    "replacement, so those sizes are optimistic.")
        else:
            high = shown[(shown["rate"] > ALPHA) & ~shown["finding"].isin(NULL_KEEPS)]
            if len(high):
                lines.append("- **Above α = .05:** " + "; ".join(
                    f"{r.finding} ({r.rate:.0%}" + (f"; {why[r.finding]}" if r.finding in why else "") + ")"
                    for r in high.itertuples()) + ". Redrawn studies share participants, so a rate shows the "
                    f"{who}cohort's own difference as well as chance.")
    if len(untested):
        lines.append("- **Not tested:** " + "; ".join(f"{r.finding} ({r.statistic})" for r in untested.itertuples()) + ".")
    if check_line:
        lines.append(f"- **Predictive check** (`fit/check/check.md`, the study's own participants): {check_line}")
    lines += ["", "## Findings", ""]
    body = []
    for r in table.itertuples():
        if not planted and r.finding == "switch":
            continue
        found = "not tested" if not getattr(r, "tested", True) else "yes" if r.holds else "no"
        body.append([r.text, r.statistic, "–" if not np.isfinite(r.p) else fmt_p(r.p), found,
                     "yes" if r.expected else "no",
                     "–" if r.rate is None or (isinstance(r.rate, float) and math.isnan(r.rate)) else f"{r.rate:.0%}",
                     r.size_for_power or "", r.paper])
    lines.append(markdown_table(["finding", "statistic", "p", "found", "expected",
                                 "power" if planted else "rate found", "size for 0.8", "paper"], body))
    lines += ["", "## Steps", ""]
    lines.append(markdown_table(["step", "seconds"], [[k, f"{v['seconds']:.0f}"] for k, v in steps.done.items()]))
    checked = "`fit/check/check.md`, " if check_line else ""
    fitted = "`fit/comparison.md`, " if depths else ""
    lines += ["", f"Total this run: {seconds:.0f} s. Files: `{'people' if people else 'sim'}/`, `analysis/report.md`, {fitted}"
                  f"{checked}`participants.csv`, `findings.csv`, `power.csv`."]
    return "\n".join(lines) + "\n"
