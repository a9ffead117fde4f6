"""Model comparison of a fit: winners, summed BIC, random-effects BMS, and parameters between conditions."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.analysis import fmt_p, markdown_table, permutation_p, save_figure
from overhang_framework.fit.bms import bms
from overhang_framework.fit.run import POOLED
from overhang_framework.results import atomic_write_text

#: Resamples of the permutation tests between conditions.
N_RESAMPLES = 10_000


def per_participant(fits: pd.DataFrame) -> pd.DataFrame:
    return fits[~fits["participant"].astype(str).str.startswith(POOLED)]


def winners(fits: pd.DataFrame) -> pd.DataFrame:
    """Each participant's best model by BIC (its row of fits.csv)."""
    df = per_participant(fits)
    return df.loc[df.groupby("participant")["bic"].idxmin()].reset_index(drop=True)


def comparison(fits: pd.DataFrame, out: Path, seed: int = 0) -> str:
    """Write ``comparison.md``, ``comparison.csv`` and ``comparison.png`` from ``fits``; return the markdown."""
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
    counts = win["model"].value_counts().reindex(models, fill_value=0)
    summed = bic.sum()
    rows = []
    result = bms(-bic.to_numpy() / 2, seed=seed) if len(models) > 1 else None
    for j, m in enumerate(models):
        row = {"model": m, "summed_bic": float(summed[m]), "delta_summed_bic": float(summed[m] - summed.min()),
               "participants_best": int(counts[m])}
        if result is not None:
            row.update(frequency=float(result.frequencies[j]), ep=float(result.ep[j]), pxp=float(result.pxp[j]))
        rows.append(row)
    table = pd.DataFrame(rows)
    atomic_write_text(out / "comparison.csv", table.to_csv(index=False))
    lines += [f"{len(pids)} participants, {len(models)} models; each participant's best model by BIC, the BIC "
              "summed over participants, and random-effects Bayesian model selection on log evidence -BIC/2 "
              "(Stephan et al. 2009; protected exceedance probabilities, Rigoux et al. 2014).", ""]
    header = ["model", "Σ BIC", "Δ Σ BIC", "best for"] + (["frequency", "EP", "PXP"] if result is not None else [])
    body = []
    for r in rows:
        cells = [r["model"], f"{r['summed_bic']:.1f}", f"{r['delta_summed_bic']:.1f}", r["participants_best"]]
        if result is not None:
            cells += [f"{r['frequency']:.3f}", f"{r['ep']:.3f}", f"{r['pxp']:.3f}"]
        body.append(cells)
    lines.append(markdown_table(header, body))
    if result is not None:
        lines += ["", f"Bayesian omnibus risk (the probability that all models are equally frequent): {result.bor:.3f}."]
    lines += ["", "## Conditions", ""] + _conditions(win, seed)
    pooled = fits[fits["participant"].astype(str).str.startswith(POOLED)]
    if len(pooled):
        best = pooled.loc[pooled.groupby("participant")["bic"].idxmin()]
        lines += ["", "## Each condition pooled", "",
                  markdown_table(["condition", "best model", "sigma", "beta", "lapse", "BIC"],
                                 [[r.condition, r.model, "" if pd.isna(r.sigma) else f"{r.sigma:g}", f"{r.beta:.2f}",
                                   f"{r.lapse:.3f}", f"{r.bic:.1f}"] for r in best.itertuples()])]
    lines += ["", "Files: `fits.csv` (every participant x model), `comparison.csv`, `comparison.png`.", "",
              "![comparison.png](comparison.png)"]
    _figure(table, win, result is not None, out)
    text = "\n".join(lines) + "\n"
    atomic_write_text(out / "comparison.md", text)
    return text


def _conditions(win: pd.DataFrame, seed: int) -> list[str]:
    conditions = sorted(c for c in win["condition"].unique() if c != "mixed")
    if len(conditions) != 2:
        return [f"Parameters are compared between two conditions; this fit has {len(conditions)}."]
    a, b = conditions
    rows = []
    for name, label in (("depth", "depth of the best model"), ("beta", "beta of the best model"),
                        ("sigma", "sigma of the best model (IPE winners)"), ("lapse", "lapse of the best model")):
        xa = win[win["condition"] == a][name].dropna().to_numpy(dtype=float)
        xb = win[win["condition"] == b][name].dropna().to_numpy(dtype=float)
        if len(xa) < 2 or len(xb) < 2:
            rows.append([label, f"{xa.mean():.3f}" if len(xa) else "", f"{xb.mean():.3f}" if len(xb) else "", "",
                         "too few"])
            continue
        p = permutation_p(xa, xb, N_RESAMPLES, seed)
        rows.append([label, f"{xa.mean():.3f} (n = {len(xa)})", f"{xb.mean():.3f} (n = {len(xb)})", fmt_p(p), ""])
    return [markdown_table(["parameter", a, b, "p", ""], rows), "",
            f"p: permutation test of the difference of means (participants as units, {N_RESAMPLES} resamples)."]


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
    for i, n in enumerate(table["participants_best"]):
        ax.text(0, i, f" best for {n}", va="center", fontsize=8)
    if has_bms:
        ax = axes[0][1]
        ax.barh(y, table["pxp"], color="#d0452f")
        ax.set_yticks(y, table["model"])
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel("protected exceedance probability")
    fig.tight_layout()
    save_figure(fig, out / "comparison.png")
