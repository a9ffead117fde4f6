"""A study's participant table and the paper's findings tested on it, one by one (:data:`FINDINGS`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from overhang_framework.studies.power import rates, resample


#: Study name -> (cohort config, participants overrides, planted).
STUDIES = {"dual_transition": ("dual_transition", ["predictor=hybrid"], True),
           "null": ("null_effect", ["predictor=ipe"], False),
           "paper_calibrated": ("paper_calibrated", ["predictor=hybrid"], True),
           "paper_people": ("paper_people", [], True),
           "graded_budgets": ("graded_budgets", [], True)}
#: Studies of several time limits between subjects (:mod:`overhang_framework.studies.graded`): their findings are each
#: level's figures and the trends across the levels, with the participants per level a lab needs.
GRADED = ("graded_budgets",)
#: The participants of a study of people (``people/``, beside their log): their ids and conditions. Not named
#: ``participants.csv``, which beside a log is a simulation's truth, and which the fit would read as one.
PEOPLE = "people.csv"
ALPHA = 0.05
#: Towers of at most EARLY blocks are early, of at least LATE blocks late (Fig. 4's crossover).
EARLY, LATE = 3, 5
#: The BMS criterion of the hybrid finding.
PXP = 0.95
#: Permutations of each test inside the power resamples (the report's own tests use the analysis's 10,000).
POWER_PERMUTATIONS = 1_000
#: Study sizes, as multiples of the cohort's, redrawn when a planted finding's power is below 0.8.
MULTIPLES = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
TARGET_POWER = 0.8


@dataclass(frozen=True)
class Finding:
    name: str
    text: str
    #: what the paper reports, and so what the planted study should show
    paper: str


FINDINGS = (
    Finding("overhang", "average overhang lower under time pressure", "1.321 against 1.460, p < .001"),
    Finding("stable", "no difference in the stable proportion", "70.2% against 67.8%, p = .482"),
    Finding("gamma", "Γ lower under time pressure", "0.15 against 0.24, p = .022"),
    Finding("vertical", "placements nearer the centre under time pressure (Fig. 3a)",
            "in words: more vertical stacking under time pressure, clearer later"),
    Finding("baseline", "both approximate models beat the veridical one (Fig. 4)", "both, p < .001"),
    Finding("crossover", "the CNN overtakes the IPE as blocks accumulate (Fig. 4)", "the CNN ahead later, p < .001"),
    Finding("depth", "fitted depth lower under time pressure", "shallower lookahead under time pressure"),
    Finding("hybrid", "the hybrid family wins (BMS)", "a dual transition, IPE-like early and CNN-like late"),
    Finding("switch", "the fitted switch point within one stage of the planted one", "(planted study only)"),
)
TL, UN = "time_limited", "unconstrained"
#: The analyses a study runs on its log.
ANALYSES = ("table1", "gamma", "flows", "prediction")
#: What a finding of the fit says in a study without one.
NO_FIT = "not tested: no fit (--no-fit)"


# --- per-participant quantities ------------------------------------------------------------------------

def participant_table(out: Path, fitted: bool = True, data: str = "sim") -> pd.DataFrame:
    """One row per participant: condition, the true parameters (none for people), Table 1's and Γ's values, Fig. 4's
    log-likelihood differences, the best model by BIC, the share of their placements the fit's grid could not map
    (``unmapped_share``: people do not place on a grid), and each family's evidence (``evidence_<family>``); with
    ``fitted`` false, the fit's columns empty (a study without a fit). ``data``: the folder of ``out`` that holds
    the participants (``sim``, simulated; ``people``, from a log)."""
    table = out / data / (PEOPLE if data == "people" else "participants.csv")
    truth = pd.read_csv(table, dtype={"id": str}).rename(columns={"id": "participant"})
    truth = truth.rename(columns={c: f"true_{c}" for c in ("sigma", "depth", "beta", "lapse", "switch", "risk",
                                                            "percept", "hand") if c in truth.columns})
    t1 = pd.read_csv(out / "analysis" / "table1_participants.csv")[
        ["participant", "stable_pct", "avg_overhang", "reward_per_trial"]]
    gamma = pd.read_csv(out / "analysis" / "gamma_participants.csv")[["participant", "gamma"]]
    lateral = out / "analysis" / "fig3a_lateral.csv"
    lateral = pd.read_csv(lateral)[["participant", "abs_x_late"]] if lateral.exists() else \
        pd.DataFrame(columns=["participant", "abs_x_late"])
    fig4 = pd.read_csv(out / "analysis" / "fig4_placements.csv")
    rows = []
    for pid, at in fig4.groupby("participant", sort=True):
        early, late = at[at["n_blocks"] <= EARLY], at[at["n_blocks"] >= LATE]
        lead = (late["ll_cnn"] - late["ll_ipe"]).mean() - (early["ll_cnn"] - early["ll_ipe"]).mean() \
            if len(early) and len(late) else np.nan
        rows.append({"participant": pid, "ipe_vs_veridical": float((at["ll_ipe"] - at["ll_veridical"]).mean()),
                     "cnn_vs_veridical": float((at["ll_cnn"] - at["ll_veridical"]).mean()), "cnn_lead": lead})
    prediction = pd.DataFrame(rows, columns=["participant", "ipe_vs_veridical", "cnn_vs_veridical", "cnn_lead"])
    from overhang_framework.fit.compare import per_participant, winners
    from overhang_framework.fit.equivalence import one_model, with_neutral

    if not fitted:
        best = pd.DataFrame(columns=["participant", "best_model", "best_family", "fitted_depth", "fitted_switch"])
        df = truth
        for part in (t1, gamma, lateral, prediction, best):
            part = part.copy()
            part["participant"] = part["participant"].astype(str)
            df = df.merge(part, on="participant", how="left")
        return df.sort_values("participant").reset_index(drop=True)
    fits = pd.read_csv(out / "fit" / "fits.csv")
    best = winners(fits)[["participant", "model", "family", "depth", "switch", "n", "unmapped"]].rename(
        columns={"model": "best_model", "family": "best_family", "depth": "fitted_depth", "switch": "fitted_switch"})
    best["unmapped_share"] = best["unmapped"] / (best["n"] + best["unmapped"])
    best = best.drop(columns=["n", "unmapped"])
    # the risk of one model fitted to every participant (its grid includes risk-neutral), never the winners' own
    risked = one_model(with_neutral(fits), "risk") if "risk" in fits.columns else None
    if risked is not None:
        rows = per_participant(with_neutral(fits))
        rows = rows[rows["model"].astype(str) == risked]
        best = best.merge(rows[["participant", "risk"]].rename(columns={"risk": "fitted_risk"}), on="participant",
                          how="left")
    people = per_participant(fits)
    evidence = {}
    for family, at in people.groupby("family"):
        table = at.pivot_table(index="participant", columns="model", values="bic")
        e = -table.to_numpy() / 2
        evidence[f"evidence_{family}"] = pd.Series(np.logaddexp.reduce(e, axis=1) - math.log(e.shape[1]),
                                                   index=table.index)
    evidence = pd.DataFrame(evidence).reset_index().rename(columns={"index": "participant"})
    df = truth
    for part in (t1, gamma, lateral, prediction, best, evidence):
        part = part.copy()
        part["participant"] = part["participant"].astype(str)
        df = df.merge(part, on="participant", how="left")
    return df.sort_values("participant").reset_index(drop=True)


# --- the findings --------------------------------------------------------------------------------------

def _perm(a: np.ndarray, b: np.ndarray, n: int, seed: int) -> float:
    from overhang_framework.behaviour.analysis import permutation_p

    return permutation_p(a, b, n, seed)


def _one_sample(x: np.ndarray) -> tuple[float, float]:
    from scipy.stats import ttest_1samp

    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan"), float("nan")
    return float(x.mean()), float(ttest_1samp(x, 0.0).pvalue)


def family_pxp(df: pd.DataFrame, seed: int = 0) -> dict[str, float]:
    """Protected exceedance probability of each family (random-effects BMS over families)."""
    from overhang_framework.fit.bms import bms

    cols = [c for c in df.columns if c.startswith("evidence_")]
    e = df[cols].to_numpy(dtype=float)
    e = e[np.isfinite(e).all(axis=1)]
    if len(cols) < 2 or not len(e):
        return {c[len("evidence_"):]: float("nan") for c in cols}
    result = bms(e, seed=seed)
    return {c[len("evidence_"):]: float(p) for c, p in zip(cols, result.pxp)}


def evaluate(df: pd.DataFrame, permutations: int = 10_000, seed: int = 0) -> dict[str, dict]:
    """Every finding of :data:`FINDINGS` on the participants of ``df``: its statistic, p and whether it holds."""
    tl, un = df[df["condition"] == TL], df[df["condition"] == UN]
    out = {}

    def compare(name: str, column: str, want_lower: bool = True) -> None:
        a, b = tl[column].to_numpy(dtype=float), un[column].to_numpy(dtype=float)
        p = _perm(a, b, permutations, seed)
        ma, mb = float(np.nanmean(a)) if np.isfinite(a).any() else np.nan, \
            float(np.nanmean(b)) if np.isfinite(b).any() else np.nan
        lower = ma < mb
        out[name] = {"statistic": f"{ma:.3f} ({TL}) against {mb:.3f} ({UN})", "p": p,
                     "holds": bool(np.isfinite(p) and p < ALPHA and lower == want_lower), "effect": ma - mb}

    compare("overhang", "avg_overhang")
    stable = tl["stable_pct"].to_numpy(dtype=float), un["stable_pct"].to_numpy(dtype=float)
    p = _perm(*stable, permutations, seed)
    out["stable"] = {"statistic": f"{np.nanmean(stable[0]):.1f}% against {np.nanmean(stable[1]):.1f}%", "p": p,
                     "holds": bool(np.isfinite(p) and p >= ALPHA),
                     "effect": float(np.nanmean(stable[0]) - np.nanmean(stable[1]))}
    compare("gamma", "gamma")
    if "abs_x_late" in df.columns and df["abs_x_late"].notna().any():
        compare("vertical", "abs_x_late")
    else:
        out["vertical"] = {"statistic": "not tested: the analysis has no flows", "p": float("nan"), "holds": False,
                           "effect": float("nan"), "tested": False}
    mi, pi = _one_sample(df["ipe_vs_veridical"].to_numpy(dtype=float))
    mc, pc = _one_sample(df["cnn_vs_veridical"].to_numpy(dtype=float))
    out["baseline"] = {"statistic": f"LL_ipe − LL_vrd {mi:+.3f}, LL_cnn − LL_vrd {mc:+.3f}",
                       "p": float(np.nanmax([pi, pc])) if np.isfinite([pi, pc]).all() else float("nan"),
                       "holds": bool(mi > 0 and mc > 0 and pi < ALPHA and pc < ALPHA), "effect": min(mi, mc)}
    ml, pl = _one_sample(df["cnn_lead"].to_numpy(dtype=float))
    out["crossover"] = {"statistic": f"LL_cnn − LL_ipe, late minus early {ml:+.3f}", "p": pl,
                        "holds": bool(np.isfinite(pl) and pl < ALPHA and ml > 0), "effect": ml}
    fitted = "fitted_depth" in df.columns and pd.to_numeric(df["fitted_depth"], errors="coerce").notna().any()
    if fitted:
        compare("depth", "fitted_depth")
    else:
        out["depth"] = {"statistic": NO_FIT, "p": float("nan"), "holds": False, "effect": float("nan"), "tested": False}
    pxp = family_pxp(df, seed)
    top = max(pxp, key=lambda k: (pxp[k] if np.isfinite(pxp[k]) else -1)) if pxp else None
    if not fitted:
        out["hybrid"] = {"statistic": NO_FIT, "p": float("nan"), "holds": False, "effect": float("nan"), "top": None,
                         "tested": False}
    elif len(pxp) < 2:  # a fit of one family cannot tell families apart
        out["hybrid"] = {"statistic": f"not tested: the fit has {'only the ' + next(iter(pxp)) + ' family' if pxp else 'no family'}",
                         "p": float("nan"), "holds": False, "effect": float("nan"), "top": top, "tested": False}
    else:
        out["hybrid"] = {"statistic": ", ".join(f"{k} {v:.2f}" for k, v in sorted(pxp.items())) + " (PXP)",
                         "p": float("nan"), "holds": bool(pxp.get("hybrid", 0) > PXP), "effect": pxp.get("hybrid"),
                         "top": top}
    hybrid = df[(df["best_family"] == "hybrid") & df.get("true_switch", pd.Series(np.nan, index=df.index)).notna()]
    if not fitted:
        out["switch"] = {"statistic": NO_FIT, "p": float("nan"), "holds": False, "effect": float("nan"),
                         "tested": False}
    elif "true_switch" in df.columns and len(hybrid):
        error = (hybrid["fitted_switch"] - hybrid["true_switch"]).abs()
        out["switch"] = {"statistic": f"fitted and planted differ by {error.mean():.2f} stages on average, over "
                                      f"{len(hybrid)} hybrid winners ({(error <= 1).mean():.0%} within one)",
                         "p": float("nan"), "holds": bool(error.mean() <= 1), "effect": float(error.mean())}
    else:
        out["switch"] = {"statistic": "no planted switch point" if "true_switch" not in df.columns
                         else "no participant's best model is a hybrid", "p": float("nan"), "holds": False,
                         "effect": float("nan")}
    return out


#: Findings a null cohort keeps: no difference in the stable proportion, and approximate physics (its participants
#: judge with a noisy IPE, so both approximate models beat the veridical one there too).
NULL_KEEPS = ("stable", "baseline")
#: Planted parameters a finding's per-participant statistic is checked against (:func:`diagnostics`).
TRUTHS = ("true_beta", "true_sigma", "true_lapse", "true_depth", "true_switch")


def expected(finding: str, planted: bool) -> bool:
    """Whether a study should show ``finding``: a planted one each, a null one only :data:`NULL_KEEPS`."""
    return True if planted else finding in NULL_KEEPS


def diagnostics(df: pd.DataFrame) -> dict[str, str]:
    """What the simulated cohort says about a finding's mechanism, where its truth columns can say it:

    * ``gamma``: each condition's mean Γ by planted depth (the paper's effect needs Γ to fall with the
      truncated depth);
    * ``hybrid``: how often the hybrid is the best family, by planted switch point (a switch point that leaves
      the IPE few decisions makes a hybrid that the fit cannot tell from the CNN).
    """
    out = {}
    if "true_depth" in df.columns and df["true_depth"].notna().any():
        parts = []
        for depth, at in df[df["true_depth"].notna()].groupby("true_depth"):
            by = at.groupby("condition")["gamma"].agg(["mean", "size"])
            means = [f"{by.at[c, 'mean']:.3f} ({c}, n = {int(by.at[c, 'size'])})" for c in (TL, UN) if c in by.index]
            parts.append(f"depth {int(depth)}: " + ", ".join(means))
        out["gamma"] = "mean Γ by planted depth, " + "; ".join(parts)
    if "true_switch" in df.columns and df["true_switch"].notna().any() and "best_family" in df.columns:
        parts = [f"{int((at['best_family'] == 'hybrid').sum())} of {len(at)} planted with switch point {int(switch)}"
                 for switch, at in df[df["true_switch"].notna()].groupby("true_switch")]
        out["hybrid"] = "the hybrid is the best family for " + ", ".join(parts)
    if "cnn_lead" in df.columns and df["cnn_lead"].notna().sum() >= 10:
        from scipy.stats import spearmanr

        from overhang_framework.behaviour.analysis import p_is

        found = []
        for column in TRUTHS:
            if column not in df.columns:
                continue
            both = df[["cnn_lead", column]].dropna()
            if len(both) >= 10 and both[column].nunique() >= 3:
                rho, p = spearmanr(both["cnn_lead"], both[column])
                if np.isfinite(rho) and p < 0.05:
                    name = {"true_beta": "β", "true_sigma": "σ", "true_switch": "switch point"}.get(
                        column, column.removeprefix("true_"))
                    found.append((abs(rho), f"{name} (Spearman ρ = {rho:+.2f}, {p_is(p)})"))
        out["crossover"] = ("each participant's late-minus-early CNN lead goes with the planted "
                            + "; ".join(t for _, t in sorted(found, reverse=True))) if found else \
            "no planted parameter goes with each participant's late-minus-early CNN lead"
    return out


def power(df: pd.DataFrame, sizes: dict[str, int], resamples: int, seed: int,
          on_resample: Callable[[], None] = lambda: None) -> dict[str, float]:
    """The share of ``resamples`` studies of ``sizes`` redrawn from ``df`` (:func:`~overhang_framework.studies.power.
    resample`) in which each finding holds."""
    rng = np.random.default_rng(seed)

    def test(study: pd.DataFrame, b: int) -> dict[str, tuple[bool, bool]]:
        found = evaluate(study, POWER_PERMUTATIONS, seed + b)
        return {name: (found[name]["holds"], found[name].get("tested", True)) for name in found}

    return rates([f.name for f in FINDINGS], resamples, lambda: resample(df, sizes, rng), test, on_resample)
