"""The graded-budget study's predictions and design: per-level figures with intervals, trends across the levels,
and the participants per level a lab needs to see each trend.

The paper asks how prediction and planning co-adapt "under graded resource constraints". A graded study
assigns each participant one of several time limits per placement (between subjects); its levels are
ordered by the time they leave, the unlimited one last. From a participant table (one row per
participant: ``condition``, Table 1's ``avg_overhang`` and ``stable_pct``, ``gamma``, the best model's
``fitted_depth`` and, where the fit has the axis, ``fitted_risk`` and ``fitted_K`` of one model fitted to every
participant; :func:`overhang_framework.studies.findings.participant_table`, or :func:`fitted` from a fit's ``fits.csv``
alone, the own-noise fit's included)
this module gives:

* **predictions**: each level's mean of each measure, with a 95% percentile bootstrap interval over the
  level's participants (:data:`DRAWS` draws, seeded);
* **trends**: Spearman's ρ between each measure and the level's rank (more time, higher rank), its two-sided
  p from permuting the level labels over the participants (:data:`PERMUTATIONS`), and whether it goes the
  expected way (:data:`MEASURES`: more time, larger overhang, larger Γ, placements further from the centre
  (Fig. 3a's flows, :func:`overhang_framework.behaviour.flows.lateral`), deeper plans, less risk aversion, more
  mental simulations; no trend in the stable proportion);
* **power and sample sizes**: for each of :data:`SIZES` participants per level, the share of studies of that
  size, drawn with replacement from the simulated pool, in which the trend holds (p < ``alpha`` in the expected
  direction); the smallest size whose power reaches :data:`TARGET_POWER` (none when no size of the grid does).

Every function sorts its rows first, so its answer does not depend on their order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.studies.power import rates, resample

#: Bootstrap draws of each interval, and permutations of each trend's test.
DRAWS = 2_000
PERMUTATIONS = 2_000
#: Permutations of each test inside the power resamples.
POWER_PERMUTATIONS = 500
ALPHA = 0.05
TARGET_POWER = 0.8
#: Participants per level at which power is estimated: from 4, where a trend over four levels can first be tested.
SIZES = (4, 5, 6, 8, 10, 12, 15, 20, 30, 40, 60, 80, 120, 160)
#: Redrawn studies behind each power figure (its Monte Carlo error is at most 0.5 / sqrt(RESAMPLES), 0.016).
RESAMPLES = 1_000


@dataclass(frozen=True)
class Measure:
    name: str
    column: str
    label: str
    #: +1: expected to grow with time; -1: to shrink; 0: no trend expected
    direction: int


MEASURES = (
    Measure("overhang", "avg_overhang", "average overhang", +1),
    Measure("stable", "stable_pct", "stable proportion (%)", 0),
    Measure("gamma", "gamma", "Γ", +1),
    Measure("lateral", "abs_x_late", "lateral reach: distance of placements from the centre, step 3 on (m)", +1),
    Measure("depth", "fitted_depth", "fitted depth", +1),
    Measure("risk", "fitted_risk", "fitted risk aversion", -1),
    Measure("K", "fitted_K", "fitted number of mental simulations (K)", +1),
)
#: The parameters :func:`fitted` takes from one model fitted to every participant, and their columns.
FITTED = {"K": "fitted_K", "risk": "fitted_risk"}


#: Measures renamed since tables were kept, old name to new: the lateral reach was once called "vertical", which is
#: what Fig. 3a calls its opposite (placements near the centre, stacked).
RENAMED = {"vertical": "lateral"}


def read_table(path: str | Path) -> pd.DataFrame:
    """A kept predictions, trends or power table (CSV), its measures under their names of today (:data:`RENAMED`)."""
    df = pd.read_csv(path)
    if "measure" in df.columns:
        df["measure"] = df["measure"].replace(RENAMED)
    return df


def levels_of(limits: Mapping[str, Optional[float]]) -> list[str]:
    """The conditions ordered by the time they leave per placement (``None``: no limit, last)."""
    return sorted(limits, key=lambda c: (limits[c] is None, limits[c] if limits[c] is not None else 0.0, c))


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    return df.sort_values(["condition", "participant"]).reset_index(drop=True)


def predictions(df: pd.DataFrame, levels: Sequence[str], measures: Sequence[Measure] = MEASURES,
                draws: int = DRAWS, seed: int = 0) -> pd.DataFrame:
    """One row per level and measure: ``n``, the participants with a value (a fitted depth has none where the
    models tied for a participant's best differ in depth), of the level's ``participants``; the
    mean and its 95% bootstrap interval (NaN where no value)."""
    df = _sorted(df)
    rng = np.random.default_rng(seed)
    rows = []
    for measure in measures:
        if measure.column not in df.columns:
            continue
        for level in levels:
            x = df.loc[df["condition"] == level, measure.column].to_numpy(dtype=float)
            everyone = int(x.size)
            x = x[np.isfinite(x)]
            if x.size:
                means = x[rng.integers(x.size, size=(draws, x.size))].mean(axis=1)
                low, high = np.quantile(means, [0.025, 0.975])
            else:
                low = high = math.nan
            rows.append({"measure": measure.name, "level": level, "n": int(x.size), "participants": everyone,
                         "mean": float(x.mean()) if x.size else math.nan, "ci_low": float(low),
                         "ci_high": float(high)})
    return pd.DataFrame(rows, columns=["measure", "level", "n", "participants", "mean", "ci_low", "ci_high"])


def _ranks(values: np.ndarray) -> np.ndarray:
    from scipy.stats import rankdata

    return rankdata(values)


def trend(df: pd.DataFrame, levels: Sequence[str], column: str, permutations: int = PERMUTATIONS,
          seed: int = 0) -> tuple[float, float]:
    """Spearman's ρ between ``column`` and the level's rank over the participants of ``levels``, and its
    two-sided permutation p (level labels shuffled over participants); NaN when fewer than two levels have
    values."""
    df = _sorted(df)
    rank = {level: k for k, level in enumerate(levels)}
    at = df[df["condition"].isin(rank)]
    x = at[column].to_numpy(dtype=float)
    keep = np.isfinite(x)
    x, level = x[keep], at["condition"].map(rank).to_numpy(dtype=float)[keep]
    if np.unique(level).size < 2 or np.unique(x).size < 2:
        return math.nan, math.nan
    rx, rl = _ranks(x), _ranks(level)
    rx = (rx - rx.mean()) / rx.std()
    rl = (rl - rl.mean()) / rl.std()
    rho = float(np.mean(rx * rl))
    rng = np.random.default_rng(seed)
    shuffled = rng.permuted(np.broadcast_to(rl, (permutations, rl.size)), axis=1)  # one row a permutation
    null = (shuffled * rx).mean(axis=1)
    p = float((1 + np.sum(np.abs(null) >= abs(rho) - 1e-12)) / (permutations + 1))
    return rho, p


def holds(rho: float, p: float, direction: int, alpha: float = ALPHA) -> bool:
    """Whether a trend shows: p < ``alpha`` the expected way (``direction`` 0: no trend expected, so it holds
    when p >= ``alpha``)."""
    if not (np.isfinite(rho) and np.isfinite(p)):
        return False
    if direction == 0:
        return p >= alpha
    return p < alpha and math.copysign(1, rho) == direction


def trends(df: pd.DataFrame, levels: Sequence[str], measures: Sequence[Measure] = MEASURES,
           permutations: int = PERMUTATIONS, seed: int = 0) -> pd.DataFrame:
    """One row per measure: ρ, p, the expected direction and whether the trend holds."""
    rows = []
    for measure in measures:
        if measure.column not in df.columns or not df[measure.column].notna().any():
            continue  # not measured (a study without a fit has no fitted depth)
        rho, p = trend(df, levels, measure.column, permutations, seed)
        rows.append({"measure": measure.name, "rho": rho, "p": p, "direction": measure.direction,
                     "holds": holds(rho, p, measure.direction)})
    return pd.DataFrame(rows, columns=["measure", "rho", "p", "direction", "holds"])


def draw(df: pd.DataFrame, levels: Sequence[str], n: int, rng: np.random.Generator) -> pd.DataFrame:
    """A study of ``n`` participants per level drawn with replacement from ``df``'s (renamed apart)."""
    return resample(_sorted(df), {level: n for level in levels}, rng, replace=True, prefix="d")


def power(df: pd.DataFrame, levels: Sequence[str], measures: Sequence[Measure] = MEASURES,
          sizes: Sequence[int] = SIZES, resamples: int = RESAMPLES, seed: int = 0,
          on_study=lambda: None) -> pd.DataFrame:
    """One row per measure and size: the share of ``resamples`` studies of that size per level in which the
    measure's trend holds (:func:`holds`), and its Monte Carlo error ``sqrt(power (1 - power) / resamples)``
    (``mc_error``). ``on_study`` is called after each redrawn study."""
    rows = []
    for measure in measures:
        if measure.column not in df.columns or not df[measure.column].notna().any():
            continue
        for n in sizes:
            rng = np.random.default_rng([seed, n])

            def test(study: pd.DataFrame, b: int, measure: Measure = measure) -> dict[str, tuple[bool, bool]]:
                rho, p = trend(study, levels, measure.column, POWER_PERMUTATIONS, seed + b)
                return {measure.name: (holds(rho, p, measure.direction), True)}

            rate = rates([measure.name], resamples, lambda: draw(df, levels, n, rng), test, on_study)[measure.name]
            rows.append({"measure": measure.name, "per_level": int(n), "power": rate, "resamples": int(resamples),
                         "mc_error": float(np.sqrt(rate * (1 - rate) / resamples))})
    return pd.DataFrame(rows, columns=["measure", "per_level", "power", "resamples", "mc_error"])


def sample_sizes(power_table: pd.DataFrame, target: float = TARGET_POWER) -> dict[str, Optional[int]]:
    """Each measure's smallest size per level from which every size of the table reaches ``target`` power (so a
    size that reaches it by its Monte Carlo error alone, below one that does not, is not taken; None when the
    largest does not, or when no trend is expected)."""
    out: dict[str, Optional[int]] = {}
    for measure, at in power_table.sort_values("per_level").groupby("measure", sort=True):
        direction = next((m.direction for m in MEASURES if m.name == measure), 1)
        below = np.flatnonzero(at["power"].to_numpy() < target)
        first = 0 if not below.size else int(below[-1]) + 1
        out[measure] = int(at["per_level"].iloc[first]) if direction and first < len(at) else None
    return out


def _extremes(pred: pd.DataFrame, measure: str) -> str:
    """``"; lowest at `a` (x), highest at `b` (y)"``: where a measure without an expected trend differs."""
    at = pred[(pred["measure"] == measure) & np.isfinite(pred["mean"])]
    if len(at) < 2:
        return ""
    low, high = at.loc[at["mean"].idxmin()], at.loc[at["mean"].idxmax()]
    return f"; lowest at `{low['level']}` ({low['mean']:.3g}), highest at `{high['level']}` ({high['mean']:.3g})"


def too_few(study: Mapping[str, int], levels: Sequence[str]) -> bool:
    """Whether a level of ``study`` (its participants a level) has fewer than the smallest study the design considers
    (:data:`SIZES`): too few for the trend test, and for a bootstrap of them to stand for any study's power."""
    return min(study.get(lv, 0) for lv in levels) < SIZES[0]


def verdict(power_table: pd.DataFrame, study: Mapping[str, int], levels: Sequence[str]) -> Optional[str]:
    """The report's first sentence when the study (``study``: its participants a level) is too small for the planned
    test to conclude anything, saying why; None when it is not. Too small: a level with fewer participants than the
    smallest study the design considers (:data:`SIZES`), or fewer than the least any expected trend needs for
    :data:`TARGET_POWER` in ``power_table``."""
    fewest = min(levels, key=lambda lv: study.get(lv, 0))
    n = study.get(fewest, 0)
    who = f"{n} participant{'s' * (n != 1)} in its level `{fewest}`"
    if too_few(study, levels):
        return (f"**Nothing can be concluded from this study:** it has {who}, fewer than the {SIZES[0]} a level of the "
                "smallest study the design considers, below which the trend test across the levels has next to no "
                "power; what follows describes these participants, not the effect of the time allowed.")
    expected = {m.name for m in MEASURES if m.direction}
    needed = {m: s for m, s in sample_sizes(power_table).items() if m in expected and s is not None}
    if len(power_table) and n < min(needed.values(), default=math.inf):
        least = min(needed, key=needed.get) if needed else None
        why = (f"the least any expected trend needs for {TARGET_POWER:.0%} power is {needed[least]} a level (the "
               f"{dict((m.name, m.label) for m in MEASURES)[least]})" if least else
               f"no expected trend reaches {TARGET_POWER:.0%} power at any size up to "
               f"{int(power_table['per_level'].max())} a level")
        return (f"**Nothing can be concluded from this study:** it has {who}, and {why}; a trend it does not show may "
                "be there, and one it shows may be chance.")
    return None


def report(pred: pd.DataFrame, found: pd.DataFrame, power_table: pd.DataFrame, levels: Sequence[str],
           limits: Mapping[str, Optional[float]], pool: Mapping[str, int], people: bool = False,
           study: Optional[Mapping[str, int]] = None) -> str:
    """``graded.md``: the per-level predictions, the trends, and the sample sizes, in sentences and tables. ``people``:
    the participants are people (a log), not simulated; ``study``: the participants a level of the study proper,
    whose size the first sentence judges (:func:`verdict`)."""
    sizes = sample_sizes(power_table)
    label = {m.name: m.label for m in MEASURES}
    kind = "people" if people else "simulated"
    said = verdict(power_table, study, levels) if study is not None else None
    lines = ["# The graded-budget study" + (": what people did" if people else ": predictions and design"), "",
             *([said, ""] if said else []),
             "Levels, by the time they leave per placement: " + ", ".join(
                 f"`{lv}` ({'no limit' if limits[lv] is None else f'{limits[lv]:g} s'}; {pool.get(lv, 0)} "
                 f"{'person' if people and pool.get(lv, 0) == 1 else kind})"
                 for lv in levels) + ".", "", "## Each level", "",
             "| measure | " + " | ".join(levels) + " |", "|---|" + "---|" * len(levels)]
    partial = []
    for measure, at in pred.groupby("measure", sort=False):
        cells = []
        for level in levels:
            row = at[at["level"] == level]
            if not len(row) or not np.isfinite(row["mean"].iloc[0]):
                cells.append("")
                continue
            r = row.iloc[0]
            some = "participants" in r and int(r["n"]) < int(r["participants"])
            cells.append(f"{r['mean']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]"
                         + (f" (n = {int(r['n'])} of {int(r['participants'])})" if some else ""))
            if some and label.get(measure, measure) not in partial:
                partial.append(label.get(measure, measure))
        if not any(cells):
            continue  # not measured
        lines.append(f"| {label.get(measure, measure)} | " + " | ".join(cells) + " |")
    lines += ["", "(mean over the level's participants, 95% bootstrap interval"
              + (f"; n = k of N: {', '.join(partial)} over the k participants whose best model has the axis, "
                 "its trend and power likewise" if partial else "") + ")", "", "## Trends and sample sizes", ""]
    for _, r in found.iterrows():
        what = label.get(r["measure"], r["measure"])
        n = sizes.get(r["measure"])
        if not np.isfinite(r["rho"]):
            values = pred.loc[(pred["measure"] == r["measure"]) & np.isfinite(pred["mean"]), "mean"]
            lines.append(f"- **{what}**: the same for every participant"
                         + (f" ({float(values.iloc[0]):g})" if len(values) and values.nunique() == 1 else "")
                         + ", so no trend can be tested.")
            continue
        if r["direction"] == 0:
            lines.append(f"- **{what}**: no trend expected; ρ = {r['rho']:+.2f}, p = {r['p']:.3f} "
                         f"({'none found' if r['holds'] else 'a trend found'}){_extremes(pred, r['measure'])}.")
            continue
        way = "grows" if r["direction"] > 0 else "shrinks"
        found_text = ("show" if r["holds"] else "do not show") if people else \
            ("shows" if r["holds"] else "does not show")
        pool_n = min(pool.get(level, 0) for level in levels)
        at_n = power_table[(power_table["measure"] == r["measure"]) & (power_table["per_level"] == n)]
        error = (f" ({float(at_n['power'].iloc[0]):.2f} ± {float(at_n['mc_error'].iloc[0]):.2f}, the share of "
                 f"{int(at_n['resamples'].iloc[0]):,} redrawn studies ± its Monte Carlo error)"
                 if n is not None and len(at_n) and "mc_error" in at_n.columns else "")
        size = (f"{n} participants per level give 80% power{error}" if n is not None else
                f"No size up to {int(power_table['per_level'].max())} per level gives 80% power"
                if len(power_table) else "Power was not estimated")
        if n is not None and n > pool_n:
            size += f" (optimistic: drawn from a pool of {pool_n} per level)"
        lines.append(f"- **{what}** {way} with the time allowed, as expected: ρ = {r['rho']:+.2f}, p = "
                     f"{r['p']:.3g}; {'these people' if people else 'the simulated pool'} {found_text} it. {size}.")
    if not len(power_table):
        why = (f": a bootstrap of fewer than {SIZES[0]} people a level says nothing of a larger study"
               if people and study is not None and too_few(study, levels) else "")
        return "\n".join(lines + ["", f"(power not estimated{why})", ""])
    lines += ["", "| measure | " + " | ".join(str(s) for s in sorted(power_table["per_level"].unique())) + " |",
              "|---|" + "---|" * power_table["per_level"].nunique()]
    for measure, at in power_table.groupby("measure", sort=False):
        at = at.sort_values("per_level")
        lines.append(f"| {label.get(measure, measure)} | " + " | ".join(f"{v:.2f}" for v in at["power"]) + " |")
    flat = [label.get(r["measure"], r["measure"]) for _, r in found.iterrows()
            if r["direction"] == 0 and r["measure"] in set(power_table["measure"])]
    counts = sorted({int(v) for v in power_table["resamples"]}) if "resamples" in power_table.columns else []
    lines += ["", "(power: the share of studies of that many participants per level, drawn with replacement from "
              + ("these people (a bootstrap: it gives the power of the effect they happen to show)" if people else
                 "the simulated pool") + ", in which the trend holds at p < .05 the expected way"
              + (f"; {', '.join(f'{c:,}' for c in counts)} redrawn studies a figure, each within about "
                 f"{max(0.5 / np.sqrt(min(counts)), 0.0):.3f} of its limit (one Monte Carlo standard error at most)"
                 if counts else "")
              + (f"; for {', '.join(flat)}, of which no trend is expected, the share in which none shows" if flat
                 else "") + "; a pool smaller than the size makes it optimistic)", ""]
    return "\n".join(lines)


def fitted(fits: pd.DataFrame) -> tuple[pd.DataFrame, dict[str, str]]:
    """The fitted measures of a fit's ``fits.csv`` (the score tables' fit or the own-noise fit,
    :mod:`overhang_framework.fit.marginal`), one row per participant: ``condition``, the best models' depth
    (``fitted_depth``: NaN where the models tied for a participant's best differ in depth) and each parameter of
    :data:`FITTED` the fit has, from one model fitted to every participant, its grid including the neutral value
    (:func:`overhang_framework.fit.equivalence.one_model`), never from each participant's winner. Also which model
    each parameter came from."""
    from overhang_framework.fit.compare import winners
    from overhang_framework.fit.equivalence import (
        one_model,
        per_participant,
        with_neutral,
    )

    fits = with_neutral(fits)
    people = per_participant(fits)
    best = winners(fits)
    first = people.drop_duplicates("participant")
    conditions = first.set_index(first["participant"].astype(str))["condition"]
    out = pd.DataFrame({"participant": best["participant"].astype(str)})
    out["condition"] = out["participant"].map(conditions)
    out["fitted_depth"] = best["depth"].to_numpy(dtype=float)
    models = {}
    for name, column in FITTED.items():
        model = one_model(fits, name) if name in fits.columns else None
        if model is None:
            continue
        rows = people[people["model"].astype(str) == model].drop_duplicates("participant")
        out[column] = out["participant"].map(rows.set_index(rows["participant"].astype(str))[name].astype(float))
        models[name] = model
    return out.sort_values("participant").reset_index(drop=True), models


def limits_of(conditions: Sequence[str]) -> dict[str, Optional[float]]:
    """Each condition's time limit per placement from its config (``conf/condition``; None: no limit)."""
    from overhang_framework.config import compose_config, group_options
    from overhang_framework.errors import OverhangError

    known = group_options("condition")
    unknown = sorted(set(conditions) - set(known))
    if unknown:
        raise OverhangError(f"unknown condition {unknown[0]!r}: the levels are conditions of conf/condition "
                            f"({', '.join(known)})")
    out = {}
    for name in conditions:
        limit = compose_config([f"condition={name}"]).condition.get("time_limit")
        out[name] = None if limit is None else float(limit)
    return out


def _truth_lines(truth: pd.DataFrame, people: pd.DataFrame, levels: Sequence[str]) -> list[str]:
    """The simulated truth (:func:`_truth_file`'s, ids as ``participant``) beside the fitted values, a row per
    parameter the truth has."""
    truth = truth.assign(participant=truth["participant"].astype(str))
    at = people.merge(truth, on="participant", how="left", suffixes=("", "_truth"))
    rows = []
    for name, column in (("depth", "fitted_depth"), *FITTED.items()):
        if name not in at.columns or column not in at.columns:
            continue
        cells = []
        for level in levels:
            x = at[at["condition"] == level]
            true, fit = x[name].to_numpy(dtype=float), x[column].to_numpy(dtype=float)
            both = np.isfinite(true) & np.isfinite(fit)
            values = ", ".join(f"{v:g}: {int(np.sum(true == v))}" for v in np.unique(true[np.isfinite(true)]))
            cells.append(f"{values} ({int(np.sum(true[both] == fit[both]))} of {int(both.sum())} fitted at it)")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    return ["## The simulated truth", "", "| parameter | " + " | ".join(levels) + " |",
            "|---|" + "---|" * len(levels), *rows, "",
            "(each level's true values, how many participants have each, and how many are fitted at their own)", ""]


def _fit_file(path: Path) -> pd.DataFrame:
    fits = pd.read_csv(path)
    if not {"participant", "condition", "model", "bic", "depth"} <= set(fits.columns):
        raise ValueError(f"{path} is not a fit's fits.csv: it needs participant, condition, model, depth and bic")
    return fits


def _truth_file(path: Path) -> pd.DataFrame:
    truth = pd.read_csv(path).rename(columns={"id": "participant"})
    if "participant" not in truth.columns:
        raise ValueError(f"{path} is not a participants.csv: it has no id (or participant) column")
    return truth


def _number(x: float) -> Optional[float]:
    return round(float(x), 4) if np.isfinite(x) else None


def _together(frames: Sequence[pd.DataFrame]) -> pd.DataFrame:
    """Several fits (or truths) of separately simulated cohorts as one, each participant named by its file's
    number (``2:sim-tl-001``) when there is more than one file."""
    if len(frames) == 1:
        return frames[0]
    out = []
    for k, frame in enumerate(frames, start=1):
        frame = frame.copy()
        frame["participant"] = f"{k}:" + frame["participant"].astype(str)
        out.append(frame)
    return pd.concat(out, ignore_index=True)


def _fitted_study(args) -> int:
    """``--fits``: a graded study's predictions, trends and sample sizes of the fitted measures of a fit."""
    import json
    import sys
    import time

    from overhang_framework.errors import OverhangError
    from overhang_framework.progress import progress_bar
    from overhang_framework.results import atomic_write_text

    started = time.perf_counter()
    try:
        if args.truth and len(args.truth) != len(args.fits):
            raise ValueError(f"give one --truth for each --fits ({len(args.fits)}), in the same order")
        fits = _together([_fit_file(path) for path in args.fits])
        people, models = fitted(fits)
        present = sorted(people["condition"].dropna().astype(str).unique())
        chosen = args.levels.split(",") if args.levels else present
        missing = sorted(set(chosen) - set(present))
        if missing:
            raise OverhangError(f"no participant of level {missing[0]!r} in {', '.join(map(str, args.fits))} (it has "
                                f"{', '.join(present)})")
        limits = limits_of(chosen)
        truth = _together([_truth_file(path) for path in args.truth]) if args.truth else None
    except (OSError, ValueError, OverhangError) as err:
        why = str(getattr(err, "strerror", None) or err).strip().splitlines()[0]
        print(f"error: {why}", file=sys.stderr)
        return 2
    levels = levels_of(limits)
    people = people[people["condition"].isin(levels)].reset_index(drop=True)
    measures = [m for m in MEASURES if m.column in people.columns and people[m.column].notna().any()]
    pred = predictions(people, levels, measures, seed=args.seed)
    found = trends(people, levels, measures, seed=args.seed)
    # a measure the same for everyone has no trend in any redrawn study either
    spread = [m for m in measures if people[m.column].dropna().nunique() > 1]
    bar = progress_bar(total=len(spread) * len(SIZES) * args.resamples, desc="power", unit="study",
                       disable=not args.resamples, mininterval=1.0, dynamic_ncols=True)
    try:
        table = power(people, levels, spread, resamples=args.resamples, seed=args.seed,
                      on_study=lambda: bar.update(1)) if args.resamples else \
            pd.DataFrame(columns=["measure", "per_level", "power", "resamples", "mc_error"])
    finally:
        bar.close()
    pool = {c: int((people["condition"] == c).sum()) for c in levels}
    text = report(pred, found, table, levels, limits, pool, study=pool)
    source = "; ".join(f"{name} of `{model}`" for name, model in models.items())
    files = " and ".join(f"`{path}`" for path in args.fits) + (
        " (their participants told apart by the file's number, `1:`, `2:`, ...)" if len(args.fits) > 1 else "")
    text += ("\n## Where the fitted measures come from\n\n" + f"{files}: the depth of each participant's best "
             "models (by BIC; none where tied best models differ in depth)"
             + (f", and {source}, the one model fitted to every participant whose summed BIC is lowest (its grid "
                "includes the neutral value), never each participant's winner" if source else "") + ".\n\n")
    if truth is not None:
        text += "\n".join(_truth_lines(truth, people, levels))
    text += f"\nTotal: {time.perf_counter() - started:.0f} s.\n"
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        for name, frame in (("participants.csv", people), ("predictions.csv", pred), ("trends.csv", found),
                            ("power.csv", table)):
            atomic_write_text(args.out / name, frame.to_csv(index=False))
        atomic_write_text(args.out / "graded.md", text)
    means = {m: {r["level"]: round(float(r["mean"]), 4) for _, r in at.iterrows()}
             for m, at in pred.groupby("measure", sort=True)}
    counts = {m.name: {level: {f"{m.name}={v:g}": int(n) for v, n in
                               people.loc[people["condition"] == level, m.column].value_counts().sort_index().items()}
                       for level in levels} for m in measures if m.name in ("depth", *FITTED)}
    print(json.dumps({"levels": levels, "models": models, "sample_sizes": sample_sizes(table),
                      "means": means, "counts": counts, "resamples": int(args.resamples),
                      "trends": {r["measure"]: {"rho": _number(r["rho"]), "p": _number(r["p"]),
                                                "holds": bool(r["holds"])} for _, r in found.iterrows()}},
                     sort_keys=True))
    if args.out is not None:
        print(f"wrote {args.out / 'graded.md'}", file=sys.stderr)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m overhang_framework.graded POWER.csv``: each measure's sample size (the smallest per level whose
    power reaches 80%) and that power with its Monte Carlo error, as JSON, from a study's ``power.csv``.
    ``python -m overhang_framework.graded --fits FITS.csv [--out DIR]``: the predictions, trends and sample sizes of
    the fitted measures (depth, risk, ``K``) of any fit of a graded study's participants (:func:`fitted`)."""
    import argparse
    import json
    import sys

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.graded",
                                 description="The sample sizes of a graded study's power.csv, as JSON; or, with "
                                             "--fits, the graded study of a fit's fitted measures.")
    ap.add_argument("power", nargs="?", default=None,
                    help="a graded study's power.csv (python -m overhang_framework.study graded_budgets)")
    ap.add_argument("--fits", type=Path, action="append", default=None,
                    help="a fit's fits.csv (python -m overhang_framework.fit or .fit.marginal) of participants of "
                         "the levels: their fitted depth, risk and K across the levels (repeatable: separately "
                         "simulated cohorts pooled, their participants told apart by the file's number)")
    ap.add_argument("--out", type=Path, default=None,
                    help="with --fits: where the tables and graded.md go (default: the summary on stdout only)")
    ap.add_argument("--levels", default=None,
                    help="with --fits: the conditions compared, comma-separated (default: every one in the fit); "
                         "ordered by their time limits")
    ap.add_argument("--truth", type=Path, action="append", default=None,
                    help="with --fits: the simulated participants' participants.csv, shown beside the fitted values "
                         "(one for each --fits, in the same order)")
    ap.add_argument("--resamples", type=int, default=RESAMPLES,
                    help=f"redrawn studies behind each power figure (default {RESAMPLES:,}; 0: no power)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.fits is not None:
        if args.power is not None:
            print("error: give a power table or --fits, not both", file=sys.stderr)
            return 2
        if args.resamples < 0:
            print(f"error: --resamples must be a whole number >= 0, got {args.resamples}", file=sys.stderr)
            return 2
        return _fitted_study(args)
    if args.power is None:
        print("error: give a power.csv, or --fits FITS.csv", file=sys.stderr)
        return 2
    try:
        table = read_table(args.power)
    except (OSError, ValueError) as err:
        why = str(getattr(err, "strerror", None) or err).strip().splitlines()[0]
        print(f"error: {args.power}: cannot read a power table ({why})", file=sys.stderr)
        return 2
    missing = [c for c in ("measure", "per_level", "power", "resamples") if c not in table.columns]
    if missing:
        print(f"error: {args.power} is not a graded study's power.csv: no column {missing[0]!r}", file=sys.stderr)
        return 2
    out = {}
    for measure, n in sample_sizes(table).items():
        row = table[(table["measure"] == measure) & (table["per_level"] == n)] if n is not None else table.iloc[0:0]
        out[measure] = {"per_level": n, "power": float(row["power"].iloc[0]) if len(row) else None,
                        "mc_error": float(row["mc_error"].iloc[0]) if len(row) and "mc_error" in row.columns else None,
                        "resamples": int(row["resamples"].iloc[0]) if len(row) else None,
                        "smallest_tried": int(table["per_level"].min()),
                        "by_size": {f"n{int(r['per_level'])}": float(r["power"])
                                    for _, r in table[table["measure"] == measure].iterrows()}}
    print(json.dumps(out, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
