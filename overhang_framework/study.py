"""Planted, null and graded studies: ``python -m overhang_framework.study {dual_transition,null,paper_calibrated,paper_people,graded_budgets}
--out DIR``.

Can the whole pipeline find the paper's dual transition where it is present, and not find it where
it is absent? A study simulates a cohort of known participants, analyses their log as a lab would
analyse people's, fits the models, checks the fits, and reports the paper's findings one by one:

* ``dual_transition`` (``cohort=dual_transition``, ``predictor=hybrid``): the paper's hypothesis by
  construction. Every participant is a hybrid (the IPE below its own switch point, the CNN from it on);
  both conditions intend the same searches (depth 1 or 2), and the 5 s budget truncates the time-limited
  ones. Each finding below should be there.
* ``null`` (``cohort=null_effect``, ``predictor=ipe``): one predictor family, no switch, and the same
  myopic search in both conditions, which the budget never truncates. None should be there, beyond chance.
* ``paper_calibrated`` (``cohort=paper_calibrated``, ``predictor=hybrid``): people like the paper's, each
  condition's distributions of depth, σ, β, lapse and decision time fitted to the paper's Table 1 and Γ
  (:mod:`overhang_framework.behaviour.calibrate`; docs/fidelity.md says which it matches and which not).
  A fit of one family (the others deleted from the fit's ``models``) leaves the family finding untested,
  and says so.
* ``paper_people`` (``cohort=paper_people``, which names its own predictor, the hybrid): the paper's people
  with the axes of docs/people.md (risk aversion, a hand planned for, perceptual noise), each condition
  calibrated to the paper's Table 1 and Γ by direct simulation.
* ``graded_budgets`` (``cohort=graded_budgets``): those people under four time limits between subjects, the
  study the paper calls for. Its findings are each level's figures and the trends across the levels, with the
  participants per level a lab needs for 80% power (:mod:`overhang_framework.graded`); the steps are the same.

The steps, each continued where it stopped when the command is run again with the same settings:
``sim/`` (:mod:`overhang_framework.participants`), ``analysis/`` (Table 1, Γ, Fig. 4 of
:mod:`overhang_framework.analyze`), ``fit/`` (:mod:`overhang_framework.fit`, the default model space with
the hybrid's switch point fitted, score tables in ``scores.sqlite``), then ``study.md``, ``findings.csv``,
``power.csv`` and ``participants.csv`` (one row per participant: every quantity a finding tests), and last
``fit/check/`` (:mod:`overhang_framework.fit.check`, the study's own participants, not the pool's others),
whose first finding ``study.md`` then adds.

Participants simulated already (say, each condition's run at the paper's size, made sitting by sitting) are
taken as they are with ``--sim DIR`` (once per run directory; each must be a finished simulation of the
study's cohort, or of another whose participants are the study's people condition by condition
(:func:`population`); no participant may appear twice, and no two runs may draw their participants from
the same random streams, i.e. the same seed, since participant ``i`` of a seed draws from the same streams in
every run): ``sim/`` then holds their logs and tables, the study proper is all of them, and power is a
bootstrap of them. A graded study's 5 s and no-limit levels are ``cohort=paper_people``'s two conditions, so
its runs serve there, and only the other levels need simulating::

    python -m overhang_framework.participants cohort=graded_budgets seed=10 \
        'cohort.participants={limit_2_5s: 40, time_limited: 0, limit_10s: 40, unconstrained: 0}' hydra.run.dir=runs/graded_new
    python -m overhang_framework.study graded_budgets --out runs/graded --sim runs/graded_new \
        --sim runs/pp_tl --sim runs/pp_un        # the paper_people runs at seeds of their own, e.g. 1 and 0

``--no-fit`` leaves out the fit (and the predictive
check); the findings of the fit (depth, hybrid, switch) are then reported as not tested::

    python -m overhang_framework.study paper_people --out runs/pp_study --sim runs/pp_tl --sim runs/pp_un --no-fit

The findings (:data:`FINDINGS`), each a test across participants at ``alpha = .05``:

1. ``overhang``: lower average overhang under time pressure (permutation test, Table 1);
2. ``stable``: no difference in the stable proportion (permutation test; holds when p >= alpha);
3. ``gamma``: Γ lower under time pressure (permutation test);
4. ``vertical``: placements nearer the centre under time pressure, Fig. 3a's "vertical stacking" (each
   participant's mean |x| of their placements from step 3 on, :func:`overhang_framework.behaviour.flows.lateral`;
   permutation test);
5. ``baseline``: both approximate models beat the veridical one on the executed placements (Fig. 4: each
   participant's mean ``LL_ipe - LL_veridical`` and ``LL_cnn - LL_veridical``, one-sample t-tests; holds when
   both are above 0 at p < alpha);
6. ``crossover``: the CNN overtakes the IPE as blocks accumulate (each participant's mean ``LL_cnn - LL_ipe``
   on towers of at least :data:`LATE` blocks minus that on towers of at most :data:`EARLY`; one-sample t-test);
7. ``depth``: the fitted depth (of each participant's best model by BIC) lower under time pressure
   (permutation test);
8. ``hybrid``: the hybrid family wins: random-effects BMS over families (each family's evidence the
   log-mean-exp of its models' ``-BIC/2``), protected exceedance probability above 0.95;
9. ``switch``: the fitted switch point near the planted one: among participants whose best model is a
   hybrid, the mean absolute difference at most one stage (planted study only).

A directional finding holds when its two-sided p is below ``alpha`` and the difference goes the paper's way,
so a null study shows it by chance at most ``alpha / 2`` of the time.

The study proper is the cohort's size (``--scale`` times the paper's 43 + 38): the first participants of
each condition. **Power and false positives.** Each participant's simulation, analysis and fit are their
own, so a study of the same size can be redrawn by resampling participants. ``--pool 2`` (the default)
simulates twice as many participants, and ``--resamples`` studies of the cohort's size are drawn from them
without replacement. The share of redrawn studies in which a finding holds is its power (planted) or its
false-positive rate (null). With ``--pool 1`` the draws are with replacement from the study's own
participants: a bootstrap, which gives the rate of the effect this sample happens to show (optimistic), and
the report says so. Where the planted power is below 0.8, larger studies are redrawn (1.5 to 8 times the
size; with replacement once they outgrow the pool, so optimistic) and the smallest that reaches 0.8 is
reported.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.errors import ConfigError, OverhangError
from overhang_framework.results import atomic_write_json, atomic_write_text
from overhang_framework.rundir import run_config

#: Study name -> (cohort config, participants overrides, planted).
STUDIES = {"dual_transition": ("dual_transition", ["predictor=hybrid"], True),
           "null": ("null_effect", ["predictor=ipe"], False),
           "paper_calibrated": ("paper_calibrated", ["predictor=hybrid"], True),
           "paper_people": ("paper_people", [], True),
           "graded_budgets": ("graded_budgets", [], True)}
#: Studies of several time limits between subjects (:mod:`overhang_framework.graded`): their findings are each
#: level's figures and the trends across the levels, with the participants per level a lab needs.
GRADED = ("graded_budgets",)
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

def participant_table(out: Path, fitted: bool = True) -> pd.DataFrame:
    """One row per participant: condition, the true parameters, Table 1's and Γ's values, Fig. 4's log-likelihood
    differences, the best model by BIC, and each family's evidence (``evidence_<family>``); with ``fitted`` false,
    the fit's columns empty (a study without a fit)."""
    truth = pd.read_csv(out / "sim" / "participants.csv").rename(columns={"id": "participant"})
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
    best = winners(fits)[["participant", "model", "family", "depth", "switch"]].rename(
        columns={"model": "best_model", "family": "best_family", "depth": "fitted_depth", "switch": "fitted_switch"})
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


def replaced(df: pd.DataFrame, sizes: dict[str, int]) -> bool:
    """Whether a study of ``sizes`` must draw ``df``'s participants with replacement: a condition has no more
    than the study takes (drawn without replacement, a study of all of them would be the same every time)."""
    return any(n >= int((df["condition"] == c).sum()) for c, n in sizes.items())


def resample(df: pd.DataFrame, sizes: dict[str, int], rng: np.random.Generator) -> pd.DataFrame:
    """A study of ``sizes`` participants per condition drawn from ``df``'s: without replacement when every
    condition has enough of them, else with replacement (:func:`replaced`)."""
    parts = []
    replace = replaced(df, sizes)
    for condition, n in sizes.items():
        pool = df[df["condition"] == condition]
        if len(pool) and n:
            rows = rng.integers(len(pool), size=n) if replace else rng.choice(len(pool), size=n, replace=False)
            parts.append(pool.iloc[rows])
    out = pd.concat(parts, ignore_index=True)
    out["participant"] = [f"r{i}" for i in range(len(out))]
    return out


def power(df: pd.DataFrame, sizes: dict[str, int], resamples: int, seed: int,
          on_resample: Callable[[], None] = lambda: None) -> dict[str, float]:
    """The share of ``resamples`` redrawn studies of ``sizes`` in which each finding holds."""
    rng = np.random.default_rng(seed)
    hits = {f.name: 0 for f in FINDINGS}
    tested = {f.name: 0 for f in FINDINGS}
    for b in range(resamples):
        found = evaluate(resample(df, sizes, rng), POWER_PERMUTATIONS, seed + b)
        for name in hits:
            hits[name] += int(found[name]["holds"])
            tested[name] += int(found[name].get("tested", True))
        on_resample()
    return {name: h / resamples if tested[name] else float("nan") for name, h in hits.items()}


# --- the command ---------------------------------------------------------------------------------------

def _digest(*paths: Path, extra: Any = None) -> str:
    h = hashlib.sha256(json.dumps(extra, sort_keys=True, default=str).encode())
    for path in paths:
        h.update(path.read_bytes())
    return h.hexdigest()


class Steps:
    """``steps.json``: each finished step with the digest of what it was made from, and its seconds."""

    def __init__(self, out: Path):
        self.path = out / "steps.json"
        self.done = json.loads(self.path.read_text()) if self.path.exists() else {}

    def current(self, name: str, digest: str) -> bool:
        return self.done.get(name, {}).get("digest") == digest

    def finish(self, name: str, digest: str, seconds: float) -> None:
        self.done[name] = {"digest": digest, "seconds": seconds}
        atomic_write_json(self.path, self.done)

    def seconds(self, name: str) -> Optional[float]:
        return self.done.get(name, {}).get("seconds")


def _compose(words: Sequence[str], config_name: str, what: str):
    """The config ``config_name`` with ``words``, or a one-line :class:`ConfigError` naming the step."""
    from overhang_framework.config import compose_config

    try:
        return compose_config(list(words), config_name=config_name)
    except OverhangError:
        raise
    except Exception as err:  # Hydra's composition errors: the first line says what is wrong
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{what}: {first}") from None


def run(study: str, out: Path, scale: float = 1.0, pool: float = 2.0, n_tasks: Optional[int] = None,
        jobs: int = 1, depths: Sequence[int] = (1, 2), resamples: int = 1000, replicas: int = 39, seed: int = 0,
        world: Sequence[str] = (), participants: Sequence[str] = (), fit: Sequence[str] = (),
        progress: bool = True, say: Callable[[str], None] = lambda s: None, sims: Sequence[str | Path] = (),
        fit_models: bool = True) -> dict:
    """Run ``study`` into ``out``; see the module docstring. ``sims``: finished simulations of the study's cohort
    (``python -m overhang_framework.participants`` run directories) to take as the participants instead of
    simulating them; ``fit_models`` false leaves out the fit (and the findings that need it)."""
    from omegaconf import OmegaConf

    if study not in STUDIES:
        raise ConfigError(f"unknown study {study!r}; studies: {', '.join(STUDIES)}")
    if not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise ConfigError(f"--scale must be a number > 0, got {scale!r}")
    if not isinstance(pool, (int, float)) or not math.isfinite(pool) or pool < 1:
        raise ConfigError(f"--pool must be a number >= 1, got {pool!r}")
    for name, value, low in (("--jobs", jobs, 1), ("--resamples", resamples, 0), ("--replicas", replicas, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"{name} must be a whole number >= {low}, got {value!r}")
    if sims and (scale != 1.0 or pool != 2.0 or n_tasks is not None or participants):
        raise ConfigError("--sim takes participants already simulated; --scale, --pool, --tasks and --participants "
                          "are for simulating them: leave them out")
    cohort, model, planted = STUDIES[study]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    steps = Steps(out)
    started = time.perf_counter()
    base = _compose([f"cohort={cohort}"], "participants", "--participants")
    counts = {str(k): int(v) for k, v in OmegaConf.to_container(base.cohort.participants).items()}
    sizes = {k: max(1, round(v * scale)) for k, v in counts.items()}
    simulated = {k: max(n, round(n * pool)) for k, n in sizes.items()}
    words = [f"cohort={cohort}", *model, *world, f"seed={seed}", f"jobs={jobs}", f"progress={str(progress).lower()}",
             *[f"cohort.participants.{k}={n}" for k, n in simulated.items()]]
    if n_tasks is not None:
        words.append(f"cohort.n_tasks={int(n_tasks)}")
    words += list(participants)

    fit_words = [*world, f"jobs={jobs}", f"cache={out / 'scores.sqlite'}", f"progress={str(progress).lower()}",
                 f"depths=[{','.join(str(int(d)) for d in depths)}]", *fit]
    from overhang_framework.participants import CONFIG_NAME, run as simulate

    sim_cfg = _compose(words, CONFIG_NAME, "--participants")  # both configs checked before any work
    _compose(fit_words, "fit", "--fit")

    # 1. the participants
    t0 = time.perf_counter()
    if sims:
        sizes = gather(sims, out / "sim", str(base.cohort.name), list(counts), str(sim_cfg.world.physics),
                       OmegaConf.to_container(sim_cfg, resolve=True))
        simulated = dict(sizes)
        say(f"taking {sum(sizes.values())} participants ({', '.join(f'{n} {k}' for k, n in sizes.items())}) "
            f"from {len(sims)} simulation{'s' * (len(sims) > 1)}")
    else:
        say(f"simulating {sum(simulated.values())} participants "
            f"({', '.join(f'{n} {k}' for k, n in simulated.items())})")
        simulate(sim_cfg, out / "sim")
    log = out / "sim" / "log.jsonl"
    if not steps.seconds("participants") or not steps.current("participants", _digest(log)):
        steps.finish("participants", _digest(log), time.perf_counter() - t0)

    # 2. the analyses a lab runs on people's logs
    from overhang_framework.behaviour.analysis import Settings, run as analyse

    digest = _digest(log, extra={"world": list(world), "seed": seed, "only": list(ANALYSES)})
    if not steps.current("analysis", digest):
        t0 = time.perf_counter()
        say("analysing the log (Table 1, Γ, the flows' lateral extent, Fig. 4)")
        analyse([log], out / "analysis", Settings(world_overrides=tuple(world), seed=seed,
                                                  only=ANALYSES, progress=progress))
        steps.finish("analysis", digest, time.perf_counter() - t0)
    if sims:  # the tasks each did, as the report says it
        n_tasks = int(pd.read_csv(out / "analysis" / "table1_participants.csv")["trials"].max())

    # 3. the fit
    from overhang_framework.fit.__main__ import run as fit_run

    # how the fit runs (its processes, its progress bar) does not change what it finds
    digest = _digest(log, extra=[w for w in fit_words if not w.startswith(("jobs=", "progress="))])
    if not fit_models:  # an earlier fit in ``out`` is kept, and not read
        depths, replicas = (), 0
    elif not steps.current("fit", digest):
        t0 = time.perf_counter()
        say("fitting the models")
        cfg = _compose(fit_words, "fit", "--fit")
        OmegaConf.update(cfg, "logs", [str(log.resolve())])
        OmegaConf.update(cfg, "out", str((out / "fit").resolve()))
        OmegaConf.update(cfg, "truth", None)
        fit_run(cfg)
        steps.finish("fit", digest, time.perf_counter() - t0)

    if study in GRADED:
        return _graded(out, sim_cfg, sizes, steps, resamples, seed, started, fit_models, progress)

    # 4. the findings, and their power by resampling participants
    t0 = time.perf_counter()
    pool_people, people = _participants(out, sizes, fit_models)
    found = evaluate(people, seed=seed)
    from overhang_framework.progress import progress_bar

    rows = []
    bar = progress_bar(total=resamples, desc="power", unit="study", disable=not progress or not resamples,
                       miniters=1, mininterval=0.5)
    rates = power(pool_people, sizes, resamples, seed, lambda: bar.update(1)) if resamples else {}
    bar.close()
    larger: dict[str, Optional[float]] = {}
    if planted and resamples:
        for f in FINDINGS:
            if f.name in ("stable",) or not rates.get(f.name, 1.0) < TARGET_POWER:
                continue
            larger[f.name] = None
        for multiple in MULTIPLES:
            todo = [n for n, m in larger.items() if m is None]
            if not todo:
                break
            bigger = {k: int(round(n * multiple)) for k, n in sizes.items()}
            r = power(pool_people, bigger, max(50, resamples // 2), seed + int(multiple * 100))
            for name in todo:
                if r[name] >= TARGET_POWER:
                    larger[name] = multiple
    for f in FINDINGS:
        got = found[f.name]
        rows.append({"finding": f.name, "text": f.text, "statistic": got["statistic"], "p": got["p"],
                     "holds": got["holds"], "tested": got.get("tested", True), "expected": expected(f.name, planted),
                     "rate": rates.get(f.name), "size_for_power": _size(larger.get(f.name, "n/a"), sizes),
                     "paper": f.paper})
    table = pd.DataFrame(rows)
    atomic_write_text(out / "findings.csv", table.to_csv(index=False))
    atomic_write_text(out / "power.csv", pd.DataFrame([{"finding": k, "rate": v, "resamples": resamples,
                                                         "sizes": json.dumps(sizes)} for k, v in rates.items()])
                      .to_csv(index=False))
    steps.finish("findings", "", time.perf_counter() - t0)
    why = diagnostics(pool_people)
    atomic_write_text(out / "study.md", report(study, table, steps, sizes, simulated, n_tasks, resamples, planted,
                                               depths, time.perf_counter() - started, replaced(pool_people, sizes),
                                               why=why))

    # 5. the predictive check of the study's own participants (the findings do not wait for it)
    check_line = None
    if replicas:
        from overhang_framework.fit import check

        own = sorted(people["participant"].astype(str))
        digest = _digest(out / "fit" / "fits.csv", extra={"replicas": replicas, "seed": seed, "participants": own})
        made = out / "fit" / "check" / "check.json"
        if not steps.current("check", digest):
            import shutil

            if made.exists():  # a check of earlier fits, other participants or settings: started afresh
                previous = json.loads(made.read_text())
                now = {"fits": hashlib.sha256((out / "fit" / "fits.csv").read_bytes()).hexdigest(),
                       "participants": own, "replicas": replicas, "seed": seed, "model": None}
                if any(previous.get(k) != v for k, v in now.items()):
                    shutil.rmtree(out / "fit" / "check")
            t0 = time.perf_counter()
            say(f"checking the fits of the study's {len(own)} participants ({replicas} replicas each)")
            check.run(out / "fit", out / "fit" / "check", replicas, None, str(out / "scores.sqlite"), jobs, seed,
                      progress, own)
            steps.finish("check", digest, time.perf_counter() - t0)
        check_line = _check_line(out / "fit" / "check" / "check.md")
    text = report(study, table, steps, sizes, simulated, n_tasks, resamples, planted, depths,
                  time.perf_counter() - started, replaced(pool_people, sizes), check_line, why)
    atomic_write_text(out / "study.md", text)
    return {"out": str(out), "findings": table, "report": text}


def population(config: Mapping, condition: str) -> dict:
    """What the participants of ``condition`` in a participants run of ``config`` (its ``run.json`` config, or a
    composed participants config) are drawn from and do: their parameters' distributions and decision times
    (the cohort's, with the condition's own on top, key by key), the motor noise, the task set, the condition's
    limits, the models and the world, and how many of the tasks each does (``cohort.n_tasks``); not how the
    work is done (``world.workers``, ``world.cache``). Two runs whose populations for a condition are equal
    simulate the same people there, whatever their cohorts are called (a graded study's 5 s and no-limit
    levels are ``cohort=paper_people``'s two conditions)."""
    cohort = dict(config.get("cohort") or {})
    own = dict((cohort.get("by_condition") or {}).get(condition) or {})
    world = {k: v for k, v in dict(config.get("world") or {}).items() if k not in ("workers", "cache")}
    return {
        "parameters": {**(cohort.get("parameters") or {}), **(own.get("parameters") or {})},
        "decision_time": {**(cohort.get("decision_time") or {}), **(own.get("decision_time") or {})},
        "motor": cohort.get("motor"), "n_tasks": cohort.get("n_tasks"),
        "condition": dict((config.get("conditions") or {}).get(condition) or {}),
        **{k: config.get(k) for k in ("planner", "predictor", "value", "tasks")}, "world": world,
    }


def _differences(a: Mapping, b: Mapping, prefix: str = "") -> list[str]:
    """The dotted keys where two nested configs differ (numbers equal to 9 digits are equal)."""
    out = []
    for key in sorted(set(a) | set(b), key=str):
        x, y = a.get(key), b.get(key)
        if isinstance(x, Mapping) and isinstance(y, Mapping):
            out += _differences(x, y, f"{prefix}{key}.")
        elif not _same(x, y):
            out.append(f"{prefix}{key}")
    return out


def _same(x, y) -> bool:
    """Equal values, numbers to 9 digits (a run.json keeps its numbers to 12), lists item by item."""
    if _numbers(x, y):
        return math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)):
        return len(x) == len(y) and all(_same(a, b) for a, b in zip(x, y))
    if isinstance(x, Mapping) and isinstance(y, Mapping):
        return not _differences(x, y)
    return x == y


def _numbers(*values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def gather(sims: Sequence[str | Path], into: Path, cohort: str, conditions: Sequence[str],
           physics: Optional[str] = None, config: Optional[Mapping] = None) -> dict[str, int]:
    """Take the participants of finished simulations (each a run directory of ``python -m
    overhang_framework.participants`` with ``log.jsonl`` and ``participants.csv``) as a study's: their logs and
    tables, in the order given, into ``into`` (rewritten only when they change). A simulation of ``cohort``
    is taken whole; one of another cohort is taken where its participants are this study's people: each of its
    conditions with participants must be one of ``conditions`` with the same :func:`population` as ``config``
    (the study's participants config) gives it. Returns the participants per condition, in the order of
    ``conditions``; refuses, in one line, a directory without a finished simulation, another population, one
    under another physics than ``physics``, a participant id given twice, two runs whose participants draw
    from the same random streams (the same seed and index: the same people, paired across conditions), and a
    condition with nobody."""
    logs, tables, seen, streams = [], [], {}, {}
    for where in map(Path, sims):
        if not (where / "log.jsonl").is_file() or not (where / "participants.csv").is_file():
            raise ConfigError(f"--sim {where}: no finished simulation there (log.jsonl and participants.csv); "
                              "run python -m overhang_framework.participants into it first")
        made_config = run_config(where)
        cohort_config = made_config.get("cohort")
        name = cohort_config.get("name") if isinstance(cohort_config, dict) else None
        made = made_config.get("world", {}).get("physics")
        if physics is not None and made != physics:
            raise ConfigError(f"--sim {where}: simulated under world.physics={made}, and this study's world is "
                              f"world.physics={physics} (give --world world.physics={made})")
        table = pd.read_csv(where / "participants.csv", dtype={"id": str})
        if name != cohort:
            present = [c for c in dict.fromkeys(table["condition"].astype(str))]
            if config is None:
                raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}")
            for condition in present:
                if condition not in conditions:
                    raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}, "
                                      f"and its {condition} participants are in none of the study's conditions "
                                      f"({', '.join(conditions)})")
                differ = _differences(population(made_config, condition), population(config, condition))
                if differ:
                    shown = ", ".join(differ[:4]) + (f" and {len(differ) - 4} more" if len(differ) > 4 else "")
                    raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}; "
                                      f"its {condition} participants are other people (they differ in {shown})")
        for pid in table["id"]:
            if pid in seen:
                raise ConfigError(f"--sim {where}: participant {pid} is in {seen[pid]} too; give each simulation once, "
                                  "and simulations whose participants differ (e.g. one a condition)")
            seen[pid] = where
        seed = made_config.get("seed")
        if "index" in table.columns and seed is not None:
            for index in table["index"].astype(int):
                if (seed, index) in streams:
                    raise ConfigError(f"--sim {where}: its participants draw from the same random streams (seed {seed}) "
                                      f"as {streams[(seed, index)]}'s, participant by participant, and would be paired "
                                      "across the study's conditions; simulate one of the two with another seed=")
            streams.update({(seed, int(i)): where for i in table["index"]})
        text = (where / "log.jsonl").read_text()
        logs.append(text if text.endswith("\n") or not text else text + "\n")
        tables.append(table)
    table = pd.concat(tables, ignore_index=True)
    sizes = {c: int((table["condition"] == c).sum()) for c in conditions}
    empty = [c for c, n in sizes.items() if not n]
    if empty:
        raise ConfigError(f"--sim: no {' or '.join(empty)} participants in the simulations given; a study compares "
                          f"{' and '.join(conditions)}")
    into.mkdir(parents=True, exist_ok=True)
    for path, text in ((into / "log.jsonl", "".join(logs)), (into / "participants.csv", table.to_csv(index=False))):
        if not path.exists() or path.read_text() != text:
            atomic_write_text(path, text)
    return sizes


def _participants(out: Path, sizes: dict[str, int], fitted: bool = True) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The participant table of the simulated pool (written to ``participants.csv``), and the study proper: the
    first participants of each condition, as many as ``sizes`` says (the rest of the pool only for redrawing)."""
    df = participant_table(out, fitted)
    atomic_write_text(out / "participants.csv", df.to_csv(index=False))
    pool_people = df[df["condition"].isin(sizes)]
    people = pd.concat([pool_people[pool_people["condition"] == c].sort_values("participant").head(n)
                        for c, n in sizes.items()], ignore_index=True)
    return pool_people, people


def _graded(out: Path, sim_cfg, sizes: dict[str, int], steps: "Steps", resamples: int, seed: int,
            started: float, fitted: bool = True, progress: bool = False) -> dict:
    """A graded study's step 4: each level's figures, the trends and the sample sizes (:mod:`overhang_framework.graded`)."""
    from overhang_framework import graded

    t0 = time.perf_counter()
    limits = {name: sim_cfg.conditions[name].get("time_limit") for name in sizes}
    levels = graded.levels_of(limits)
    pool_people, people = _participants(out, sizes, fitted)
    pred = graded.predictions(people, levels, seed=seed)
    found = graded.trends(people, levels, seed=seed)
    from overhang_framework.progress import progress_bar

    measured = [m for m in graded.MEASURES if m.column in pool_people.columns and pool_people[m.column].notna().any()]
    bar = progress_bar(total=len(measured) * len(graded.SIZES) * resamples, desc="power", unit="study",
                       disable=not progress or not resamples, mininterval=1.0, dynamic_ncols=True)
    try:
        table = graded.power(pool_people, levels, resamples=resamples, seed=seed, on_study=lambda: bar.update(1)) \
            if resamples else pd.DataFrame(columns=["measure", "per_level", "power", "resamples", "mc_error"])
    finally:
        bar.close()
    for name, frame in (("predictions.csv", pred), ("trends.csv", found), ("power.csv", table)):
        atomic_write_text(out / name, frame.to_csv(index=False))
    steps.finish("findings", "", time.perf_counter() - t0)
    text = graded.report(pred, found, table, levels, limits, {c: int((pool_people["condition"] == c).sum())
                                                              for c in levels})
    if not fitted:
        text += ("\nNo fit (`--no-fit`): the fitted depth and risk aversion are neither predicted nor tested; "
                 "run the study again without `--no-fit` to add them.\n")
    text += ("\n## Steps\n\n" + "\n".join(f"- {k}: {v['seconds']:.0f} s" for k, v in steps.done.items())
             + f"\n\nTotal this run: {time.perf_counter() - started:.0f} s. Files: `sim/`, `analysis/report.md`, "
             "`fit/comparison.md`, `participants.csv`, `predictions.csv`, `trends.csv`, `power.csv`.\n")
    atomic_write_text(out / "study.md", text)
    return {"out": str(out), "findings": found, "report": text}


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


def report(study: str, table: pd.DataFrame, steps: Steps, sizes: dict[str, int], simulated: dict[str, int],
           n_tasks: Optional[int], resamples: int, planted: bool, depths: Sequence[int], seconds: float,
           bootstrap: bool = False, check_line: Optional[str] = None,
           why: Optional[Mapping[str, str]] = None) -> str:
    from overhang_framework.behaviour.analysis import fmt_p, markdown_table, p_is

    why = why or {}
    n = sum(sizes.values())
    shown = table[table["finding"] != "switch"] if not planted else table
    untested = shown[~shown["tested"]] if "tested" in shown.columns else shown.iloc[:0]
    shown = shown.drop(untested.index)
    holds = shown[shown["holds"] & (shown["finding"] != "stable")]
    kind = "planted" if planted else "null"
    expected = "each finding" if planted else \
        "none of the effects of a dual transition (beyond chance), and the approximate physics its cohort keeps"
    lines = [f"# Study: {study} ({kind})", "",
             f"{n} participants ({', '.join(f'{v} {k}' for k, v in sizes.items())}), "
             f"{'all' if n_tasks is None else n_tasks} tasks each, "
             f"{'fitted depths ' + ', '.join(map(str, depths)) if depths else 'no fit'}; "
             f"the study should show {expected}.", ""]
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
                     f"simulated participants, {how}): {rates}.")
        if planted:
            low = shown[(shown["rate"] < TARGET_POWER) & (shown["finding"] != "stable")]
            if len(low):
                lines.append("- **Below 0.8:** " + "; ".join(
                    f"{r.finding} ({r.rate:.0%} at {n}; {r.size_for_power or 'not redrawn'} participants reach 0.8"
                    + (f"; {why[r.finding]}" if r.finding in why else "") + ")"
                    for r in low.itertuples()) + ". Studies larger than the simulated cohort are drawn with "
                    "replacement, so those sizes are optimistic.")
        else:
            high = shown[(shown["rate"] > ALPHA) & ~shown["finding"].isin(NULL_KEEPS)]
            if len(high):
                lines.append(f"- **Above α = .05:** " + "; ".join(
                    f"{r.finding} ({r.rate:.0%}" + (f"; {why[r.finding]}" if r.finding in why else "") + ")"
                    for r in high.itertuples()) + ". Redrawn studies share participants, so a rate shows the "
                    "simulated cohort's own difference as well as chance.")
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
    lines += ["", f"Total this run: {seconds:.0f} s. Files: `sim/`, `analysis/report.md`, {fitted}"
                  f"{checked}`participants.csv`, `findings.csv`, `power.csv`."]
    return "\n".join(lines) + "\n"


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.study", description=__doc__.split("\n\n")[0])
    ap.add_argument("study", help=f"one of: {', '.join(STUDIES)}")
    ap.add_argument("--out", required=True, help="the study's directory")
    ap.add_argument("--scale", type=float, default=1.0, help="participants per condition, share of the paper's 43 + 38")
    ap.add_argument("--pool", type=float, default=2.0,
                    help="simulate this many times the study's participants, to redraw studies from (default 2)")
    ap.add_argument("--tasks", type=int, default=None, help="tasks per participant (default: all 20)")
    ap.add_argument("--depths", default="1,2", help="fitted depths (default 1,2)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--resamples", type=int, default=1000,
                    help="redrawn studies for power (default 1000: each power within 0.016; 0: none)")
    ap.add_argument("--replicas", type=int, default=39, help="predictive check replicas (default 39; 0: no check)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--world", action="append", default=[], metavar="OVERRIDE", help="world override, every step")
    ap.add_argument("--participants", action="append", default=[], metavar="OVERRIDE",
                    help="participants override (repeatable)")
    ap.add_argument("--fit", action="append", default=[], metavar="OVERRIDE", help="fit override (repeatable)")
    ap.add_argument("--sim", action="append", default=[], metavar="DIR",
                    help="take the participants of this finished simulation of the study's cohort (or of another "
                         "whose participants are the study's people) instead of simulating (repeatable, e.g. one "
                         "run a condition); power is then a bootstrap")
    ap.add_argument("--no-fit", action="store_true", help="leave out the fit and the findings that need it")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    try:
        depths = [int(d) for d in args.depths.split(",") if d.strip()]
    except ValueError:
        print(f"error: --depths must be whole numbers separated by commas, got {args.depths!r}", file=sys.stderr)
        return 2
    try:
        summary = run(args.study, Path(args.out), args.scale, args.pool, args.tasks, args.jobs, depths, args.resamples,
                      args.replicas, args.seed, args.world, args.participants, args.fit, not args.no_progress, say,
                      args.sim, not args.no_fit)
    except OverhangError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: each finished step and part is kept; run the same command to continue", file=sys.stderr)
        return 130
    print(summary["report"].split("\n## ")[0].strip())
    print(f"\nwrote {Path(summary['out']) / 'study.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
