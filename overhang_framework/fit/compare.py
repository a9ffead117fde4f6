"""Model comparison of a fit: what was found in sentences, then winners, summed BIC, random-effects BMS,
parameters between conditions, and for simulated participants their true models beside the fitted ones.

Models that predict the same are one model (:mod:`overhang_framework.fit.equivalence`): a participant's best
model is every model tied with the lowest BIC, models tied for every participant are merged before BIC is
summed and the BMS is run, and a parameter compared between conditions is that of one model fitted to every
participant. ``python -m overhang_framework.fit.compare DIR`` writes the comparison again from ``DIR/fits.csv``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.analysis import fmt_p, markdown_table, p_is, permutation_p, save_figure
from overhang_framework.errors import ConfigError
from overhang_framework.fit.adequacy import read as read_adequacy
from overhang_framework.fit.adequacy import sentence as adequacy_sentence
from overhang_framework.fit.bms import BMSResult, bms
from overhang_framework.fit.equivalence import (TOLERANCE, best_sets, label, merge_equivalent, one_model,
                                                per_participant, with_neutral)
from overhang_framework.fit.run import POOLED
from overhang_framework.fit.scores import Model
from overhang_framework.results import atomic_write_text
from overhang_framework.rundir import run_config

#: Resamples of the permutation tests between conditions.
N_RESAMPLES = 10_000
#: The BMS separates the models when the omnibus risk is below this and one PXP above :data:`SEPARATED_PXP`.
SEPARATED_BOR = 0.05
SEPARATED_PXP = 0.95
#: A difference between conditions is reported as one below this p.
ALPHA = 0.05
#: The simulated participants' file the participants command writes next to its log.
TRUTH = "participants.csv"
#: The columns of a truth table (:func:`read_truth`).
TRUTH_COLUMNS = ["participant", "true_predictor", "true_family", "true_model", "true_depth", "depth_reached",
                 "true_sigma", "true_beta", "true_lapse", "true_switch", "true_risk", "true_hand", "true_percept"]


def winners(fits: pd.DataFrame) -> pd.DataFrame:
    """Each participant's best models by BIC, one row per participant: every model tied with the lowest BIC,
    reported as one (:func:`overhang_framework.fit.equivalence.best_sets`; ``members`` lists them, ``ties``
    counts them), with a model without an axis at its neutral value."""
    return best_sets(with_neutral(fits))


@dataclass
class Difference:
    """One parameter of the best models compared between two conditions."""

    name: str
    label: str
    a: np.ndarray
    b: np.ndarray
    p: float

    @property
    def compared(self) -> bool:
        return len(self.a) >= 2 and len(self.b) >= 2


def read_truth(paths: Sequence[Path], families: Mapping[str, str],
               records: Optional[pd.DataFrame] = None) -> Optional[pd.DataFrame]:
    """The true models and parameters of simulated participants, one row per participant (:data:`TRUTH_COLUMNS`).

    ``paths`` are ``participants.csv`` files of :mod:`overhang_framework.behaviour.simulation`; the ``run.json``
    beside each gives the generating predictor and planner (a parameter the cohort did not draw is the
    model's own setting). ``families`` maps each fitted family to its predictor's name: the true family is
    the fitted family of the generating predictor. ``records`` (the behaviour log) give ``depth_reached``,
    the median depth the participant's searches completed (a condition's budget may cut a search short).
    None when no path holds a participant.
    """
    rows = []
    for path in paths:
        path = Path(path)
        try:
            table = pd.read_csv(path)
        except (OSError, ValueError) as err:
            raise ConfigError(f"truth: cannot read {path}: {getattr(err, 'strerror', None) or err}") from None
        missing = [c for c in ("id", "sigma", "depth", "beta", "lapse") if c not in table.columns]
        if missing:
            raise ConfigError(f"truth: {path} is not a participants.csv of the participants command "
                              f"(no column {missing[0]!r})")
        config = run_config(path.parent)
        predictor = dict(config.get("predictor") or {})
        planner = dict(config.get("planner") or {})
        name = predictor.get("name")
        by_name = [f for f, n in families.items() if n == name]
        family = name if name in by_name else (by_name[0] if by_name else None)
        for r in table.itertuples(index=False):
            depth = _number(r.depth)
            if depth is None:
                depth = 1 if planner.get("name") == "myopic" else _number(planner.get("depth"))
            beta = _number(r.beta)
            if beta is None and planner.get("choice") == "softmax":
                beta = _number(planner.get("beta"))
            sigma = _number(r.sigma)
            if sigma is None:
                sigma = _number(predictor.get("sigma"))
            switch = _number(getattr(r, "switch", None))
            if switch is None:
                switch = _number(predictor.get("switch"))
            risk = _number(getattr(r, "risk", None))
            if risk is None:
                risk = _number(planner.get("risk"))
            hand, steadiness = _number(getattr(r, "hand", None)), _number(getattr(r, "steadiness", None))
            if hand is not None and steadiness is not None:  # the hand its planner planned for
                hand *= steadiness
            label = Model({"name": name}, int(depth), family).label if family and depth else None
            rows.append({"participant": str(r.id), "true_predictor": name, "true_family": family, "true_model": label,
                         "true_depth": depth, "depth_reached": None, "true_sigma": sigma, "true_beta": beta,
                         "true_lapse": _number(r.lapse), "true_switch": switch, "true_risk": risk,
                         "true_hand": hand,
                         "true_percept": _number(getattr(r, "percept", None))})
    if not rows:
        return None
    truth = pd.DataFrame(rows, columns=TRUTH_COLUMNS).drop_duplicates("participant", keep="first")
    if records is not None and "depth_completed" in records.columns:
        reached = records.groupby(records["participant"].astype(str))["depth_completed"].median()
        truth["depth_reached"] = [_number(reached.get(p)) for p in truth["participant"]]
    return truth


def _blank(value) -> str:
    """``value`` as a short number, or empty when it is missing."""
    return "" if value is None or pd.isna(value) else f"{float(value):g}"


def _number(value) -> Optional[float]:
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


def comparison(fits: pd.DataFrame, out: Path, seed: int = 0, truth: Optional[pd.DataFrame] = None,
               adequacy: Optional[Mapping] = None, motor: Optional[Mapping] = None) -> str:
    """Write ``comparison.md``, ``comparison.csv`` and ``comparison.png`` from ``fits``; return the markdown.

    The markdown opens with what was found, in sentences: first, when ``adequacy`` (the summary of
    :mod:`overhang_framework.fit.adequacy`) is given, whether any model describes the participants at all;
    ``truth`` (:func:`read_truth`) adds the simulated participants' true models and parameters beside the
    fitted ones.
    """
    fits, groups = merge_equivalent(with_neutral(fits))
    df = per_participant(fits)
    models = sorted(df["model"].unique())
    pids = sorted(df["participant"].unique())
    lines = ["# Model comparison", ""]
    if not len(df):
        lines.append("No participant was fitted.")
        text = "\n".join(lines) + "\n"
        atomic_write_text(out / "comparison.md", text)
        return text
    bic = df.pivot_table(index="participant", columns="model", values="bic").reindex(index=pids, columns=models)
    win = winners(fits)
    sole = win.loc[win["ties"] == 1, "model"].value_counts().reindex(models, fill_value=0)
    shared = pd.Series({m: int(sum(m in members for members in win.loc[win["ties"] > 1, "members"]))
                        for m in models}, dtype=int)
    summed = bic.sum()
    rows = []
    result = bms(-bic.to_numpy() / 2, seed=seed) if len(models) > 1 else None
    held = heldout_winners(fits)
    if held is not None:
        # summed over the participants every model has a held-out score for
        scored = df.pivot_table(index="participant", columns="model", values="heldout_loglik").reindex(
            index=pids, columns=models)
        held_ll = scored.dropna().sum()
        held_counts = held["model"].value_counts().reindex(models, fill_value=0)
    for j, m in enumerate(models):
        row = {"model": m, "summed_bic": float(summed[m]), "delta_summed_bic": float(summed[m] - summed.min()),
               "participants_best": int(sole[m]), "participants_tied_best": int(shared[m])}
        if result is not None:
            row.update(frequency=float(result.frequencies[j]), ep=float(result.ep[j]), pxp=float(result.pxp[j]))
        if held is not None:
            row.update(summed_heldout_loglik=float(held_ll[m]), participants_best_heldout=int(held_counts[m]))
        rows.append(row)
    table = pd.DataFrame(rows)
    atomic_write_text(out / "comparison.csv", table.to_csv(index=False))
    conditions = sorted(c for c in win["condition"].unique() if c != "mixed")
    differences = _differences(win, fits, conditions, seed) if len(conditions) == 2 else None
    truth = _matched(truth, win)
    if adequacy is not None:
        lines += [adequacy.get("sentence") or adequacy_sentence(adequacy), ""]
    lines += findings(table, result, len(pids), win, conditions, differences, truth, groups)
    lines.append(unmapped_sentence(df, motor))
    if held is not None:
        lines.append(heldout_sentence(table, win, held, int(df["folds"].dropna().iloc[0])))
    lines += ["", "## Models", "",
              f"{len(pids)} participants, {len(models)} models; each participant's best model by BIC, the BIC "
              "summed over participants, and random-effects Bayesian model selection on log evidence -BIC/2 "
              "(Stephan et al. 2009; protected exceedance probabilities, Rigoux et al. 2014).", ""]
    header = ["model", "Σ BIC", "Δ Σ BIC", "best for", "tied best for"] \
        + (["frequency", "EP", "PXP"] if result is not None else [])
    header += ["Σ held-out LL", "best for (held-out)"] if held is not None else []
    body = []
    for r in rows:
        cells = [r["model"], f"{r['summed_bic']:.1f}", f"{r['delta_summed_bic']:.1f}", r["participants_best"],
                 r["participants_tied_best"]]
        if result is not None:
            cells += [f"{r['frequency']:.3f}", f"{r['ep']:.3f}", f"{r['pxp']:.3f}"]
        if held is not None:
            cells += [f"{r['summed_heldout_loglik']:.1f}", r["participants_best_heldout"]]
        body.append(cells)
    lines.append(markdown_table(header, body))
    if result is not None:
        lines += ["", "Bayesian omnibus risk (the probability that all models are equally frequent): "
                      f"{result.bor:.3f}. The BMS is said to separate the models when it is below {SEPARATED_BOR:g} and one protected "
                      f"exceedance probability is above {SEPARATED_PXP:g}."]
    lines += ["", f"Best for: the participants whose only best model it is; tied best for: those for whom it is one "
                  f"of several models of equal likelihood (log-likelihoods within {TOLERANCE:g}, as many "
                  "parameters), which predict the same on their data and are reported as one."]
    lines += ["", "## Conditions", ""] + _conditions_table(conditions, differences)
    if truth is not None:
        lines += ["", "## Simulated participants: true and fitted", ""] + _truth_table(truth, win)
    pooled = fits[fits["participant"].astype(str).str.startswith(POOLED)]
    risked = "risk" in fits.columns and bool((fits["risk"].fillna(0) != 0).any())
    if len(pooled):
        best = best_sets(pooled, pooled=True)
        lines += ["", "## Each condition pooled", "",
                  markdown_table(["condition", "best model", "sigma", "switch"] + (["risk"] if risked else [])
                                 + ["beta", "lapse", "BIC"],
                                 [[r.condition, r.model, _blank(r.sigma),
                                   "" if pd.isna(getattr(r, "switch", None)) else f"{int(r.switch)}"]
                                  + ([_blank(getattr(r, "risk", None))] if risked else [])
                                  + [f"{r.beta:.2f}", f"{r.lapse:.3f}", f"{r.bic:.1f}"] for r in best.itertuples()])]
    lines += ["", "Files: `fits.csv` (every participant x model), `comparison.csv`, `comparison.png`.", "",
              "![comparison.png](comparison.png)"]
    _figure(table, win, result is not None, out)
    text = "\n".join(lines) + "\n"
    atomic_write_text(out / "comparison.md", text)
    return text


def unmapped_sentence(df: pd.DataFrame, motor: Optional[Mapping] = None) -> str:
    """How many of each participant's placements the fit left out because no grid action of their layer was
    within a step (``unmapped`` in fits.csv), or with a ``motor`` model (fit.json's) none could reach them, in a
    sentence that is always there."""
    if "unmapped" not in df.columns or "n" not in df.columns:
        return "- **Placements left out:** this fits.csv does not count them."
    each = df.groupby(df["participant"].astype(str))[["unmapped", "n"]].first()
    left, total = int(each["unmapped"].sum()), int((each["unmapped"] + each["n"]).sum())
    reach = ("no legal grid action of their layer within a step" if motor is None else
             f"no legal grid action of their layer that the motor noise (sd {float(motor['sd']):g} m) can reach")
    if not left:
        if motor is not None:
            return (f"- **Placements left out:** none; each of the {total:,} placements is scored where it was made "
                    f"(its x to {float(motor.get('precision', 0.001)) * 1000:g} mm, given every grid action it may "
                    f"have been planned as, with motor noise of sd {float(motor['sd']):g} m).")
        return (f"- **Placements left out:** none; every one of the {total:,} placements maps onto the world's grid "
                "(the nearest legal grid action of its layer, within a step).")
    worst = each.assign(share=each["unmapped"] / (each["unmapped"] + each["n"])).sort_values(
        ["share", "unmapped"], ascending=False)
    shown = ", ".join(f"{p} {int(r.unmapped)} of {int(r.unmapped + r.n)}" for p, r in worst.head(5).iterrows()
                      if r.unmapped)
    some = int((each["unmapped"] > 0).sum())
    return (f"- **Placements left out:** {left:,} of {total:,} ({left / total:.1%}) have {reach} and are in no "
            f"likelihood, for {some} of {len(each)} participants (the most: "
            f"{shown}).")


def heldout_winners(fits: pd.DataFrame) -> Optional[pd.DataFrame]:
    """Each participant's best model by held-out log-likelihood (its row of fits.csv); None without one."""
    if "heldout_loglik" not in fits.columns:
        return None
    df = per_participant(fits)
    if not df["heldout_loglik"].notna().any():
        return None
    complete = df.groupby("participant")["heldout_loglik"].transform(lambda s: bool(s.notna().all()))
    df = df[complete.astype(bool)]
    rows = []
    for _, at in df.groupby("participant", sort=True):
        top = at["heldout_loglik"].max()
        tied = at[at["heldout_loglik"] >= top - TOLERANCE]
        row = at.loc[at["heldout_loglik"].idxmax()].copy()
        row["model"] = label(tied["model"])
        rows.append(row)
    return pd.DataFrame(rows).reset_index(drop=True)


def heldout_sentence(table: pd.DataFrame, win: pd.DataFrame, held: pd.DataFrame, folds: int) -> str:
    """The winners by held-out likelihood set beside those by BIC, in a sentence."""
    best = table.sort_values(["summed_heldout_loglik", "model"], ascending=[False, True]).iloc[0]
    by_bic = win.set_index(win["participant"].astype(str))["model"]
    by_held = held.set_index(held["participant"].astype(str))["model"]
    common = [p for p in by_bic.index if p in by_held.index]
    differ = [p for p in common if by_bic[p] != by_held[p]]
    text = (f"- **Held-out likelihood** ({folds} folds of each participant's trials, each model fitted on the "
            f"others): {best['model']} predicts the held-out trials best (Σ held-out log-likelihood "
            f"{best['summed_heldout_loglik']:.1f}). Each participant's best model by held-out likelihood is the "
            f"one BIC picks for {len(common) - len(differ)} of {len(common)}")
    if differ:
        shown = ", ".join(f"{p} (BIC {by_bic[p]}, held-out {by_held[p]})" for p in differ[:8])
        more = f" and {len(differ) - 8} more" if len(differ) > 8 else ""
        text += f"; they disagree for {shown}{more}."
    else:
        text += "."
    bic_top = table.sort_values(["summed_bic", "model"]).iloc[0]["model"]
    if bic_top != best["model"]:
        text += f" Summed over participants, BIC favours {bic_top} and held-out likelihood {best['model']}."
    return text


def findings(table: pd.DataFrame, result: Optional[BMSResult], n: int, win: pd.DataFrame, conditions: list[str],
             differences: Optional[list[Difference]], truth: Optional[pd.DataFrame],
             groups: Sequence[Sequence[str]] = ()) -> list[str]:
    """What the comparison found, one bullet per finding: models that predict the same, the winners, the BMS,
    the conditions, the truth."""
    out = []
    same = _same_sentence(win, groups)
    if same:
        out.append(f"- **Models that predict the same:** {same}")
    if len(table) == 1:
        out.append(f"- One model was fitted ({table['model'].iloc[0]}), so there is no comparison between models.")
    else:
        ordered = table.sort_values(["summed_bic", "model"]).reset_index(drop=True)
        best, second = ordered.iloc[0], ordered.iloc[1]
        counts = ", ".join(f"{m} for {c}" for m, c in _count_order(win))
        out.append(f"- **Summed BIC:** {best['model']} fits best over the {n} participants (Σ BIC "
                   f"{best['summed_bic']:.1f}; the next, {second['model']}, is {second['delta_summed_bic']:.1f} "
                   f"higher). Each participant's best model: {counts}.")
    if result is not None:
        top = table.loc[table["pxp"].idxmax()]
        pick = (f"{top['model']} (estimated frequency {top['frequency']:.2f}, protected exceedance probability "
                f"{top['pxp']:.2f})")
        bor = "< 0.001" if result.bor < 0.001 else f"{result.bor:.3f}"
        if result.bor < SEPARATED_BOR and top["pxp"] > SEPARATED_PXP:
            text = f"separates the models: the most frequent is {pick}; the Bayesian omnibus risk is {bor}."
            best_bic = table.loc[table["summed_bic"].idxmin(), "model"]
            if best_bic != top["model"]:
                text += f" The summed BIC and the BMS favour different models ({best_bic} and {top['model']})."
        elif result.bor < SEPARATED_BOR:
            text = (f"finds that the models are not equally frequent (Bayesian omnibus risk {bor}), "
                    f"but none stands out: the likeliest to be the most frequent is {pick}.")
        else:
            text = (f"does not separate the models: the Bayesian omnibus risk (the probability that all are "
                    f"equally frequent) is {result.bor:.2f}; the highest protected exceedance probability is "
                    f"{top['pxp']:.2f}, of {top['model']}.")
        out.append(f"- **Random-effects BMS** {text}")
    if differences is None:
        out.append(f"- **Conditions:** parameters are compared between two conditions; this fit has "
                   f"{len(conditions)}.")
    else:
        out.append(f"- **Conditions** ({conditions[0]} against {conditions[1]}; the depth of each participant's best "
                   f"model, the other parameters of one model fitted to every participant): "
                   f"{_difference_sentence(differences, conditions)}")
    if truth is not None:
        out.append(f"- **Simulated participants** ({TRUTH}): {_truth_sentence(truth, win)}")
    return out


def _count_order(win: pd.DataFrame) -> list[tuple[str, int]]:
    """Each best model (a tied set as one) and its number of participants, the most frequent first."""
    counts = win["model"].astype(str).value_counts()
    return sorted(((str(m), int(c)) for m, c in counts.items()), key=lambda mc: (-mc[1], mc[0]))


def _same_sentence(win: pd.DataFrame, groups: Sequence[Sequence[str]]) -> str:
    """Which models the comparison found to predict the same, for every participant or for some, in a sentence
    or two; empty when none do."""
    parts = []
    if groups:
        merged = _join([label(g) for g in groups])
        parts.append(f"{merged} {'have' if len(groups) == 1 else 'each have'} equal likelihoods for every participant "
                     f"(within {TOLERANCE:g} of log-likelihood, as many parameters): the data cannot tell them apart, "
                     f"so they are one model here.")
    tied = win[win["ties"] > 1]
    if len(tied):
        sets = tied["model"].astype(str).value_counts()
        shown = _join([f"{m} for {c}" for m, c in sorted(sets.items(), key=lambda mc: (-mc[1], mc[0]))])
        parts.append(f"For {len(tied)} of {len(win)} participants the lowest BIC is shared by models that predict the "
                     f"same on their data ({shown}); each such set is reported as one best model, never one of "
                     "its members by name.")
    return " ".join(parts)


def _difference_sentence(differences: list[Difference], conditions: list[str]) -> str:
    a, b = conditions
    parts, same, few = [], [], []
    for d in differences:
        if not d.compared:
            few.append(f"{d.name} (n = {len(d.a)} and {len(d.b)})")
        elif d.p < ALPHA:
            ma, mb = float(np.mean(d.a)), float(np.mean(d.b))
            where, other = (b, a) if mb > ma else (a, b)
            hi, lo = max(ma, mb), min(ma, mb)
            parts.append(f"{d.name} is higher under {where} than under {other} ({hi:.3g} against {lo:.3g}, "
                         f"{p_is(d.p)})")
        else:
            same.append(f"{d.name} ({p_is(d.p)})")
    sentences = []
    if parts:
        sentences.append("; ".join(parts) + ".")
    if same:
        sentences.append(f"{_join(same)} {'does' if len(same) == 1 else 'do'} not differ at "
                         f"p < {str(ALPHA).lstrip('0')}.")
    if few:
        sentences.append(f"too few participants to compare {_join(few)}.")
    return " ".join(s[0].upper() + s[1:] for s in sentences)


def _join(items: Sequence[str]) -> str:
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


#: The parameters compared between conditions, each of one model fitted to every participant.
COMPARED = ("beta", "sigma", "switch", "risk", "hand", "percept", "lapse")


def _differences(win: pd.DataFrame, fits: pd.DataFrame, conditions: list[str], seed: int) -> list[Difference]:
    """The depth of each participant's best model (a tied set's, where its members share it), and each parameter
    of :data:`COMPARED` of one model fitted to every participant
    (:func:`overhang_framework.fit.equivalence.one_model`), between the two conditions."""
    a, b = conditions
    out = []

    def compare(name: str, text: str, rows: pd.DataFrame) -> None:
        xa = rows[rows["condition"] == a][name].dropna().to_numpy(dtype=float)
        xb = rows[rows["condition"] == b][name].dropna().to_numpy(dtype=float)
        p = permutation_p(xa, xb, N_RESAMPLES, seed) if len(xa) >= 2 and len(xb) >= 2 else float("nan")
        out.append(Difference(name, text, xa, xb, p))

    compare("depth", "depth of the best model", win)
    people = per_participant(fits)
    for name in COMPARED:
        if name not in people.columns:  # fits written before the column existed, or a fit without the axis
            continue
        model = one_model(fits, name)
        if model is None:
            continue
        rows = people[people["model"].astype(str) == model]
        if name in ("risk", "hand", "percept") and not (people[name] != 0).any():
            continue  # every model has the axis at its neutral value for every participant
        compare(name, f"{name} of {model}", rows)
    return out


def _conditions_table(conditions: list[str], differences: Optional[list[Difference]]) -> list[str]:
    if differences is None:
        return [f"Parameters are compared between two conditions; this fit has {len(conditions)}."]
    a, b = conditions
    rows = []
    for d in differences:
        cells = [f"{x.mean():.3f} (n = {len(x)})" if len(x) else "–" for x in (d.a, d.b)]
        rows.append([d.label, *cells, fmt_p(d.p) if d.compared else "too few"])
    return [markdown_table(["parameter", a, b, "p"], rows), "",
            f"p: permutation test of the difference of means (participants as units, {N_RESAMPLES} resamples). "
            "The depth is each participant's best model's (none where the models tied for best differ in depth); "
            "every other parameter is that of one model fitted to every participant, of lowest summed BIC among "
            "those that fit it on a grid, never the winners' own (which are selected). A model without an axis "
            "(risk, hand, percept) has it at its neutral value, 0; an axis that is 0 for every fit is left out."]


def _matched(truth: Optional[pd.DataFrame], win: pd.DataFrame) -> Optional[pd.DataFrame]:
    """The rows of ``truth`` of fitted participants, in the fit's order; None when there are none."""
    if truth is None or not len(truth):
        return None
    fitted = list(win["participant"].astype(str))
    truth = truth[truth["participant"].astype(str).isin(fitted)]
    if not len(truth):
        return None
    order = {p: k for k, p in enumerate(fitted)}
    return truth.sort_values("participant", key=lambda s: s.map(order)).reset_index(drop=True)


def _truth_sentence(truth: pd.DataFrame, win: pd.DataFrame) -> str:
    best = win.set_index(win["participant"].astype(str))
    n = len(truth)
    generating = truth["true_model"].fillna(truth["true_predictor"].fillna("unknown").astype(str) + " (not fitted)")
    kinds = generating.value_counts()
    models = _join([f"{m} for {c}" if len(kinds) > 1 else m for m, c in kinds.items()])
    text = f"the generating model is {models}" + (f" (all {n} participants)." if len(kinds) == 1 else ".")
    known = truth[truth["true_family"].notna()]
    if len(known):
        hits = sum(r.true_family in best.loc[r.participant, "member_families"] for r in known.itertuples())
        text += f" The generating family is the best model's for {hits} of {len(known)}"
        tied = sum(best.loc[r.participant, "ties"] > 1 and r.true_family in best.loc[r.participant, "member_families"]
                   for r in known.itertuples())
        text += (f" ({tied} of them through a set of models that predict the same, the generating family among "
                 "them)." if tied else ".")
    fitted_depth = [float(best.loc[p, "depth"]) for p in truth["participant"]]
    planned = truth["true_depth"].to_numpy(dtype=float)
    if truth["depth_reached"].notna().any():
        reached = truth["depth_reached"].to_numpy(dtype=float)
        ok = int(np.sum(np.isclose(fitted_depth, reached)))
        text += (f" The best model's depth equals the depth the participant's searches reached (the median of "
                 f"the log's depth_completed) for {ok} of {n}, and the planned depth for "
                 f"{int(np.sum(np.isclose(fitted_depth, planned)))} of {n}.")
    elif np.isfinite(planned).any():
        same = int(np.sum(np.isclose(fitted_depth, planned)))
        text += f" The best model's depth equals the planned depth for {same} of {n}."
    return text + " The table below sets the true parameters beside the fitted ones."


def _truth_table(truth: pd.DataFrame, win: pd.DataFrame) -> list[str]:
    best = win.set_index(win["participant"].astype(str))

    def num(x, digits=3) -> str:
        return "–" if x is None or (isinstance(x, float) and not np.isfinite(x)) or pd.isna(x) else f"{x:.{digits}g}"

    def shown(true: str, fitted: str) -> bool:
        """An axis's columns only where the truth or a fit gives it a value other than its neutral 0."""
        return bool((truth[true].fillna(0) != 0).any() or (fitted in win.columns and (win[fitted].fillna(0) != 0).any()))

    risked, handed, seen = shown("true_risk", "risk"), shown("true_hand", "hand"), shown("true_percept", "percept")
    rows = []
    for r in truth.itertuples(index=False):
        fit = best.loc[r.participant]
        depth = num(r.true_depth) + ("" if pd.isna(r.depth_reached) else f" ({num(r.depth_reached)})")
        rows.append([r.participant, fit["condition"], r.true_model or f"{r.true_predictor} (not fitted)", depth,
                     num(r.true_sigma), num(r.true_switch)] + ([num(r.true_risk)] if risked else [])
                    + ([num(r.true_hand)] if handed else []) + ([num(r.true_percept)] if seen else [])
                    + [num(r.true_beta), num(r.true_lapse), fit["model"], num(fit["sigma"]), num(fit.get("switch"))]
                    + ([num(fit.get("risk"))] if risked else []) + ([num(fit.get("hand"))] if handed else [])
                    + ([num(fit.get("percept"))] if seen else [])
                    + [num(fit["beta"]), num(fit["lapse"])])
    return [markdown_table(["participant", "condition", "true model", "true depth (reached)", "true sigma",
                            "true switch"] + (["true risk"] if risked else []) + (["true hand"] if handed else [])
                           + (["true percept"] if seen else []) + [
                            "true beta", "true lapse", "best model", "fitted sigma", "fitted switch"]
                           + (["fitted risk"] if risked else []) + (["fitted hand"] if handed else [])
                           + (["fitted percept"] if seen else [])
                           + ["fitted beta", "fitted lapse"], rows), "",
            "True: the participants command's draws (participants.csv) and the generating model (run.json beside "
            "it); reached: the median depth the participant's searches completed in the log. Fitted: the best "
            "model's parameters (sigma and the hybrid's switch point on the fitted grids)."]


def _figure(table: pd.DataFrame, win: pd.DataFrame, has_bms: bool, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 2 if has_bms else 1
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 0.5 * len(table) + 1.8), squeeze=False)
    y = np.arange(len(table))
    ax = axes[0][0]
    ax.barh(y, table["delta_summed_bic"], color="#2f6db5")
    ax.set_yticks(y, table["model"])
    ax.invert_yaxis()
    ax.set_xlabel("Σ BIC − best Σ BIC (lower is better)")
    for i, (n, m) in enumerate(zip(table["participants_best"], table["participants_tied_best"])):
        ax.text(0, i, f" best for {n}" + (f" (+{m} tied)" if m else ""), va="center", fontsize=8)
    if has_bms:
        ax = axes[0][1]
        ax.barh(y, table["pxp"], color="#d0452f")
        ax.set_yticks(y, table["model"])
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel("protected exceedance probability")
    fig.tight_layout()
    save_figure(fig, out / "comparison.png")


def summary(fits: pd.DataFrame, truth: Optional[pd.DataFrame] = None, seed: int = 0) -> dict:
    """The comparison's findings as plain numbers: participants, models merged as one, each best model (a tied set
    as one) and its count, the generating family's recoveries, and each parameter between two conditions."""
    fits, groups = merge_equivalent(with_neutral(fits))
    df = per_participant(fits)
    win = winners(fits)
    summed = df.groupby("model")["bic"].sum().sort_values()
    out = {"participants": int(win["participant"].nunique()), "merged": [label(g) for g in groups],
           "tied_participants": int((win["ties"] > 1).sum()), "best": dict(_count_order(win)),
           "best_summed_bic": str(summed.index[0]) if len(summed) else None}
    conditions = sorted(c for c in win["condition"].unique() if c != "mixed")
    if len(conditions) == 2:
        out["conditions"] = {d.name: {"model": d.label, conditions[0]: float(np.mean(d.a)) if len(d.a) else None,
                                      conditions[1]: float(np.mean(d.b)) if len(d.b) else None, "p": float(d.p)}
                             for d in _differences(win, fits, conditions, seed)}
    truth = _matched(truth, win)
    if truth is not None:
        best = win.set_index(win["participant"].astype(str))
        known = truth[truth["true_family"].notna()]
        hit = [r.true_family in best.loc[r.participant, "member_families"] for r in known.itertuples()]
        tied = [best.loc[r.participant, "ties"] > 1 for r in known.itertuples()]
        out.update(known=int(len(known)), recovered=int(sum(hit)),
                   recovered_through_ties=int(sum(h and t for h, t in zip(hit, tied))))
        out["parameters"] = recovered_parameters(truth, best)
    return out


def recovered_parameters(truth: pd.DataFrame, best: pd.DataFrame) -> dict:
    """How each best model's β, σ and lapse (the first of a tied set's) stand to the simulated participants' truth:
    β's median ratio fitted / true and the correlation of their logs, σ's mean absolute error, the lapse's median
    difference fitted - true; over the participants with both."""
    rows = [(best.loc[r.participant], r) for r in truth.itertuples() if r.participant in best.index]
    out: dict = {}
    pairs = [(float(b["beta"]), float(t.true_beta)) for b, t in rows
             if pd.notna(t.true_beta) and pd.notna(b["beta"]) and b["beta"] > 0]
    if pairs:
        fitted, true = np.array(pairs).T
        out["beta"] = {"median_ratio": float(np.median(fitted / true)), "n": len(pairs),
                       "r_log": float(np.corrcoef(np.log(fitted), np.log(true))[0, 1]) if len(pairs) > 2 else None}
    pairs = [(float(b["sigma"]), float(t.true_sigma)) for b, t in rows if pd.notna(t.true_sigma) and pd.notna(b["sigma"])]
    if pairs:
        fitted, true = np.array(pairs).T
        out["sigma"] = {"mean_abs_error": float(np.mean(np.abs(fitted - true))), "n": len(pairs)}
    pairs = [(float(b["lapse"]), float(t.true_lapse)) for b, t in rows if pd.notna(t.true_lapse) and pd.notna(b["lapse"])]
    if pairs:
        fitted, true = np.array(pairs).T
        out["lapse"] = {"median_difference": float(np.median(fitted - true)), "n": len(pairs)}
    return out


def families_of(spec: Mapping) -> dict[str, str]:
    """Each fitted family of a ``fit.json`` and its predictor's name (a hand's: the predictor it wraps)."""
    from overhang_framework.fit.scores import without_hand

    out = {}
    for label_, config, *_ in spec.get("models") or []:
        family = str(label_).split("/")[0]
        out.setdefault(family, str(without_hand(dict(config)).get("name")))
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m overhang_framework.fit.compare DIR [--truth CSV ...] [--log LOG ...]``: the comparison of
    ``DIR/fits.csv`` written again into ``DIR`` (comparison.md, .csv, .png)."""
    import argparse
    import json

    from overhang_framework.behaviour.log import read_log

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.fit.compare",
                                     description="Write a fit's comparison again from its fits.csv (models that "
                                                 "predict the same as one, parameters of one model), opening with "
                                                 "adequacy.json's finding when it describes that fits.csv.")
    parser.add_argument("dir", type=Path, help="a fit's directory (fits.csv and fit.json)")
    parser.add_argument("--truth", type=Path, action="append", default=None,
                        help="participants.csv of simulated participants (default: the one beside each log of "
                             "fit.json, if there)")
    parser.add_argument("--log", type=Path, action="append", default=None,
                        help="the behaviour logs, for the depth each participant's searches reached (default: "
                             "fit.json's, if there)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the BMS and permutation tests (default 0)")
    parser.add_argument("--summary", type=Path, default=None, help="also write the findings' figures to this JSON file")
    args = parser.parse_args(argv)
    try:
        fits_path = args.dir / "fits.csv"
        try:
            fits = pd.read_csv(fits_path)
        except (OSError, ValueError) as err:
            raise ConfigError(f"{fits_path}: cannot read a fit's rows ({getattr(err, 'strerror', None) or err}); "
                              "give the directory a fit wrote") from None
        missing = [c for c in ("participant", "model", "family", "loglik", "k", "bic") if c not in fits.columns]
        if missing:
            raise ConfigError(f"{fits_path} is not a fit's fits.csv: no column {missing[0]!r}")
        spec = {}
        if (args.dir / "fit.json").is_file():
            spec = json.loads((args.dir / "fit.json").read_text())
        logs = args.log if args.log is not None else [Path(p) for p in spec.get("logs") or [] if Path(p).is_file()]
        truth_paths = args.truth if args.truth is not None else [Path(p).parent / TRUTH for p in logs
                                                                 if (Path(p).parent / TRUTH).is_file()]
        records = read_log([str(p) for p in logs]) if logs else None
        truth = read_truth(truth_paths, families_of(spec), records) if truth_paths else None
    except (ConfigError, OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    fitness = read_adequacy(args.dir)
    comparison(fits, args.dir, seed=args.seed, truth=truth, adequacy=fitness, motor=spec.get("motor"))
    if args.summary is not None:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.summary, {**summary(fits, truth, args.seed),
                                         **({"adequacy": fitness} if fitness is not None else {})})
    print(f"wrote {args.dir / 'comparison.md'}" + (f" (truth: {len(truth)} simulated participants)"
                                                   if truth is not None else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
