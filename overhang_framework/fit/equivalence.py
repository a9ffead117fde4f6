"""Models that predict the same: found in a fit's likelihoods, never in the models' names.

Two models predict the same on a participant's data when their fitted log-likelihoods are equal within
:data:`TOLERANCE` and they have as many free parameters (so their BIC and AIC are equal too). That happens
where their score tables are the same numbers on the participant's states: a hybrid whose switch point sends
every tower to its IPE is that IPE there, a predictor registered under a second name is the first, and a
deterministic predictor's depth-``D`` model is its depth-``D - 1`` model on states with fewer than ``D``
placements left. The fit's optimiser is deterministic, so identical tables give identical fits to the bit;
the tolerance only absorbs the last bits of a sum taken in another order.

* Each participant's **best models** are every model tied with the lowest BIC: a set, reported as one
  (``hybrid/D2 = ipe/D2``), never reduced to one member by its name (:func:`best_sets`).
* Models tied for **every** participant that both were fitted to are one model of the fit: the comparison
  merges them into one row before it sums BIC or runs the BMS (:func:`merge_equivalent`).
* A model without an axis (risk, a hand it plans for, a percept) is that axis at its neutral value
  (:data:`NEUTRAL`), so every participant has a value of every axis (:func:`with_neutral`).
* A parameter compared between conditions comes from one model fitted to every participant, never from the
  selected winners' parameters (:func:`one_model`).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import pandas as pd

#: Two fits of one participant are tied when their log-likelihoods differ by at most this (absolute) and
#: their numbers of parameters are equal.
TOLERANCE = 1e-6
#: What tied models are joined by in a label (``hybrid/D2 = ipe/D2``).
JOIN = " = "
#: The value of each axis a model without it has: risk-neutral, no hand it plans for, no perceptual noise.
NEUTRAL = {"risk": 0.0, "hand": 0.0, "percept": 0.0}
#: The parameters a fit's rows may have, besides the model's depth.
PARAMETERS = ("sigma", "switch", "risk", "hand", "percept", "beta", "lapse")


def per_participant(fits: pd.DataFrame) -> pd.DataFrame:
    """The rows of ``fits`` of participants, not of pooled conditions."""
    from overhang_framework.fit.run import POOLED

    return fits[~fits["participant"].astype(str).str.startswith(POOLED)]


def with_neutral(fits: pd.DataFrame) -> pd.DataFrame:
    """``fits`` with every missing value of an axis of :data:`NEUTRAL` (a model without the axis, or a fit
    written before a model took the neutral value) set to that value; columns the fit has not are left out."""
    fits = fits.copy()
    for name, value in NEUTRAL.items():
        if name in fits.columns:
            fits[name] = fits[name].astype(float).fillna(value)
    return fits


def label(members) -> str:
    """The label of a set of models that predict the same: their labels, sorted, joined by :data:`JOIN`."""
    return JOIN.join(sorted({str(m) for m in members}))


def _tied(a: pd.Series, b: pd.Series) -> bool:
    return bool(int(a["k"]) == int(b["k"]) and abs(float(a["loglik"]) - float(b["loglik"])) <= TOLERANCE)


def equivalent_groups(fits: pd.DataFrame) -> list[list[str]]:
    """The models of ``fits`` (one participant's row per model) tied for every participant fitted with both,
    grouped (each group sorted; groups of one model left out). Two models fitted to no common participant are
    not grouped."""
    people = per_participant(fits)
    models = sorted(people["model"].astype(str).unique())
    by_model = {m: at.set_index(at["participant"].astype(str)) for m, at in people.groupby(people["model"].astype(str))}
    parent = {m: m for m in models}

    def root(m: str) -> str:
        while parent[m] != m:
            parent[m] = parent[parent[m]]
            m = parent[m]
        return m

    for i, a in enumerate(models):
        for b in models[i + 1:]:
            if root(a) == root(b):
                continue
            x, y = by_model[a], by_model[b]
            common = x.index.intersection(y.index)
            if not len(common):
                continue
            same_k = x.loc[common, "k"].to_numpy(dtype=float) == y.loc[common, "k"].to_numpy(dtype=float)
            gap = np.abs(x.loc[common, "loglik"].to_numpy(dtype=float) - y.loc[common, "loglik"].to_numpy(dtype=float))
            if same_k.all() and (gap <= TOLERANCE).all():
                parent[root(b)] = root(a)
    groups: dict[str, list[str]] = {}
    for m in models:
        groups.setdefault(root(m), []).append(m)
    return sorted((sorted(g) for g in groups.values() if len(g) > 1), key=lambda g: g[0])


def merge_equivalent(fits: pd.DataFrame) -> tuple[pd.DataFrame, list[list[str]]]:
    """``fits`` with each group of :func:`equivalent_groups` as one model, and the groups.

    The group's rows keep the parameters its members share (a parameter on which they differ, such as the
    IPE's sigma beside a hybrid's switch point, is left empty: the data cannot tell which it is); its label
    and family are the members' joined by :data:`JOIN`. Pooled rows are merged likewise.
    """
    groups = equivalent_groups(fits)
    if not groups:
        return fits, []
    out = fits.copy()
    out["model"] = out["model"].astype(str)
    keep = np.ones(len(out), dtype=bool)
    for group in groups:
        name = label(group)
        families = label(out.loc[out["model"].isin(group), "family"].astype(str))
        for participant, rows in out[out["model"].isin(group)].groupby(out["participant"].astype(str)):
            first = rows.index[0]
            for column in PARAMETERS + ("depth",):
                if column in out.columns:
                    values = rows[column].to_numpy(dtype=float)
                    if not _all_same(values):
                        out.loc[first, column] = np.nan
            out.loc[first, ["model", "family"]] = [name, families]
            keep[out.index.get_indexer(rows.index[1:])] = False
    return out[keep].reset_index(drop=True), groups


def _all_same(values: np.ndarray) -> bool:
    values = np.asarray(values, dtype=float)
    missing = np.isnan(values)
    if missing.all():
        return True
    if missing.any():
        return False
    return bool(np.allclose(values, values[0], rtol=1e-9, atol=1e-12))


def best_sets(fits: pd.DataFrame, pooled: bool = False) -> pd.DataFrame:
    """Each participant's (``pooled``: each pooled condition's) best models by BIC, one row per participant:
    the lowest-BIC row's columns, with
    ``model`` and ``family`` the tied set's labels (:func:`label`), ``ties`` the number of models in it,
    ``members`` their labels and ``member_families`` their families (lists), and a parameter the set's
    members do not share (``depth`` included) left empty."""
    people = per_participant(fits)
    if pooled:
        people = fits[~fits.index.isin(people.index)]
    if not len(people):
        return people.assign(ties=pd.Series(dtype=int), members=pd.Series(dtype=object),
                             member_families=pd.Series(dtype=object))
    rows = []
    for participant, at in people.groupby(people["participant"].astype(str), sort=True):
        at = at.sort_values(["bic", "model"], kind="stable")
        top = at.iloc[0]
        tied = at[[_tied(top, r) for _, r in at.iterrows()]]
        row = top.copy()
        row["participant"] = top["participant"]
        row["model"] = label(tied["model"]) if len(tied) > 1 else str(top["model"])
        families = sorted({str(f) for m in tied["family"] for f in str(m).split(JOIN)})
        row["family"] = JOIN.join(families)
        for column in PARAMETERS + ("depth",):
            if column in at.columns and not _all_same(tied[column].to_numpy(dtype=float)):
                row[column] = np.nan
        row["ties"] = int(len(tied))
        row["members"] = sorted(str(m) for m in tied["model"])
        row["member_families"] = families
        rows.append(row)
    return pd.DataFrame(rows).reset_index(drop=True)


def one_model(fits: pd.DataFrame, name: str) -> Optional[str]:
    """The model whose ``name`` parameter the conditions compare: of the models fitted to every participant with
    a value of ``name`` for each, those whose value varies between participants (a fitted grid), else all of
    them; of those, the one of lowest summed BIC (equal sums: the models predict the same, and either gives
    the same values). None when no model has a value for every participant."""
    people = per_participant(fits)
    if name not in people.columns or not len(people):
        return None
    everyone = people["participant"].astype(str).nunique()
    candidates = []
    for model, at in people.groupby(people["model"].astype(str)):
        values = at[name].to_numpy(dtype=float)
        if at["participant"].astype(str).nunique() < everyone or np.isnan(values).any():
            continue
        candidates.append((not _all_same(values), -float(at["bic"].sum()), model))
    if not candidates:
        return None
    varying = [c for c in candidates if c[0]] or candidates
    best = max(c[1] for c in varying)
    return sorted(c[2] for c in varying if math.isclose(c[1], best, rel_tol=0, abs_tol=2 * TOLERANCE * everyone))[0]
