"""Parameter and model recovery: ``python -m overhang_framework.fit.recovery --out DIR [OVERRIDES ...]``.

Simulates participants whose models and parameters are known (the simulated
participants of :mod:`overhang_framework.behaviour.simulation`, one group per
*generating model* of ``conf/recovery.yaml``), fits the model space to them
(:mod:`overhang_framework.fit`), and reports in ``DIR``:

* ``recovery.md``: parameter recovery (true against fitted ``sigma``, ``beta``
  and lapse under the generating model index, with correlations and errors), the
  confusion matrix of the fitted depth (within the generating family), and the
  confusion matrix of the winning model (by BIC) against the generating one;
* ``recovery.png`` (the scatter plots and both matrices), ``recovery.csv``
  (one row per participant: truth, the winner, the fit under the true model)
  and ``recovery.json`` (the headline figures);
* ``sim/`` (each generator's simulation, and ``log.jsonl`` with them all,
  participant ids prefixed by the generator) and ``fit/`` (the fit).

Every participant does the unconstrained condition, so every search is whole
and its depth is the drawn one. A stopped run continues when run again into
the same ``DIR`` (the simulations continue from their parts, the fit from the
score cache). Overrides are Hydra's, on ``conf/recovery.yaml``::

    python -m overhang_framework.fit.recovery --out runs/recovery
    python -m overhang_framework.fit.recovery --out runs/recovery participants=40 jobs=2 \\
        '~generators.hybrid' '~models.hybrid'

``--config-name recovery_explanations`` recovers explanations instead of predictor families: one generator
per source of error (shallow planning, dynamics noise, risk aversion, a hand planned for, perceptual noise),
each generator's ``family`` naming the fitted family that stands for it and its ``parameters`` replacing
those it draws differently; the report adds the new axes' recovery and each generator's BMS.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from overhang_framework.errors import ConfigError, OverhangError
from overhang_framework.fit.__main__ import _plain, _whole
from overhang_framework.results import atomic_write_json, atomic_write_text

log = logging.getLogger("overhang_framework.fit.recovery")
CONFIG_NAME = "recovery"
#: The recovery configs ``--config-name`` may choose: the predictor families', the explanations' of
#: docs/people.md (``conf/recovery_explanations.yaml``) and risk aversion's where predictions are unsure
#: (``conf/recovery_risk_unsure.yaml``).
CONFIGS = (CONFIG_NAME, "recovery_explanations", "recovery_risk_unsure")
TOP = ("world", "value", "out", "seed", "generators", "participants", "tasks", "n_tasks", "parameters", "models",
       "depths", "states", "cache", "jobs", "progress")
#: The condition every simulated participant does.
CONDITION = "unconstrained"
#: The axes of a participant beyond the paper's whose truth and fit (on a grid) the report sets side by side.
AXES = ("risk", "hand", "percept")
#: The targets of the issue this command reports against (share of participants, correlation).
TARGETS = {"depth": 0.8, "family": 0.8, "sigma_r": 0.8}


def check_config(cfg: DictConfig) -> dict:
    """The checked settings of a recovery run (nothing simulated or fitted)."""
    from overhang_framework.fit.space import model_space
    from overhang_framework.plugins import Registry

    registry = Registry()
    extra = [k for k in cfg if k not in TOP and k != "hydra"]
    if extra:
        raise ConfigError(f"unknown config key '{extra[0]}'; top-level keys: {', '.join(sorted(TOP))}")
    if not cfg.get("out"):
        raise ConfigError("no results directory given: add --out DIR")
    for key, minimum in (("seed", 0), ("participants", 1), ("n_tasks", 1), ("jobs", 1)):
        _whole(cfg, key, minimum)
    generators = _plain(cfg.generators) or {}
    if not isinstance(generators, Mapping) or not generators:
        raise ConfigError("generators must name at least one generating model, e.g. {ipe: {predictor: ipe}}")
    for name, spec in generators.items():
        if isinstance(spec, Mapping) and spec.get("parameters") is not None and not isinstance(spec["parameters"], Mapping):
            raise ConfigError(f"generators.{name}.parameters must be a mapping of parameter names to distributions "
                              f"(as cohort.parameters), got {spec['parameters']!r}")
        if not isinstance(spec, Mapping):
            raise ConfigError(f"generators.{name} must be a mapping with a predictor name and its settings, "
                              f"got {spec!r}")
        if not str(name).replace("_", "").isalnum():
            raise ConfigError(f"generator name {name!r} must be letters, digits and underscores")
        predictor = str(spec.get("predictor", name))
        if predictor not in registry.names("predictor"):
            raise ConfigError(f"generators.{name}: unknown predictor {predictor!r}; registered: "
                              f"{', '.join(sorted(registry.names('predictor')))}")
    from overhang_framework.fit.fitting import STATES

    if cfg.get("states") not in STATES:
        raise ConfigError(f"states must be one of {', '.join(STATES)}, got {cfg.get('states')!r}")
    depths = _plain(cfg.depths)
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    tasks = tasks_from_config(compose_config([f"tasks={cfg.tasks}"], config_name="participants").tasks)
    blocks = max((len(t.sequence) for t in tasks), default=None)
    space = model_space(_plain(cfg.models) or {}, depths if isinstance(depths, list) else [depths], blocks)
    fitted = {}  # predictor name -> the first fitted family that uses it
    for family, spec in (_plain(cfg.models) or {}).items():
        fitted.setdefault(str((spec or {}).get("predictor", family)), str(family))
    families = {}
    labels = {index.family for index in space}
    for name, spec in generators.items():
        predictor = str(spec.get("predictor", name))
        if spec.get("family") is not None:  # the fitted family that stands for this generator's explanation
            if str(spec["family"]) not in labels:
                raise ConfigError(f"generators.{name}.family: {spec['family']!r} is not a fitted family; fitted "
                                  f"families: {', '.join(sorted(labels))}")
            families[str(name)] = str(spec["family"])
            continue
        if predictor not in fitted:
            raise ConfigError(f"generators.{name} uses the predictor {predictor!r}, which no fitted family uses; "
                              f"fitted families: {', '.join(f'{f} ({p})' for p, f in fitted.items())}")
        families[str(name)] = fitted[predictor]
    return {"generators": generators, "out": Path(str(cfg.out)).expanduser().resolve(), "space": space,
            "families": families}


def participants_config(cfg: DictConfig, name: str, spec: Mapping[str, Any], index: int) -> DictConfig:
    """The participants command's config that simulates generator ``name``'s participants."""
    from overhang_framework.config import compose_config
    from overhang_framework.plugins import Registry, accepted_parameters

    settings = dict(spec)
    predictor = str(settings.pop("predictor", name))
    settings.pop("family", None)
    own = dict(settings.pop("parameters", None) or {})
    registry = Registry()  # check_config has refused unknown predictors
    shipped = predictor in _predictor_configs()
    base = compose_config([f"predictor={predictor}"] if shipped else [], config_name="participants")
    base.predictor = OmegaConf.merge(base.predictor if shipped else {"name": predictor}, settings)
    parameters = {**dict(_plain(cfg.parameters)), **own}
    takes = accepted_parameters(registry.get("predictor", predictor).factory)
    if takes is not None and "sigma" not in takes:
        parameters["sigma"] = None
    base.world = _plain(cfg.world)
    base.value = _plain(cfg.value)
    base.tasks = compose_config([f"tasks={cfg.tasks}"], config_name="participants").tasks
    base.cohort.name = f"recovery-{name}"
    base.cohort.participants = {CONDITION: int(cfg.participants)}
    base.cohort.n_tasks = int(cfg.n_tasks)
    base.cohort.parameters = parameters
    base.seed = int(cfg.seed) * 1000 + index
    base.jobs = int(cfg.jobs)
    base.progress = bool(cfg.progress)
    return base


def _predictor_configs() -> list[str]:
    from overhang_framework.config import group_options

    return group_options("predictor")


def simulate(cfg: DictConfig, out: Path, generators: Mapping[str, Mapping[str, Any]],
             families: Mapping[str, str]) -> tuple[Path, pd.DataFrame]:
    """Simulate every generator's participants; one log with them all, and the truth (one row each;
    ``family``: the fitted family of the generator's predictor)."""
    from overhang_framework.behaviour import simulation as sim

    lines, truth = [], []
    for index, (name, spec) in enumerate(generators.items()):
        where = out / "sim" / name
        config = participants_config(cfg, name, spec, index)
        summary = sim.run(config, where)
        log.info("generator %s: %s", name, summary)
        for line in (where / sim.LOG).read_text().splitlines():
            if line.strip():
                record = json.loads(line)
                record["participant"] = f"{name}-{record['participant']}"
                lines.append(json.dumps(record))
        table = pd.read_csv(where / sim.CSV)
        table["participant"] = [f"{name}-{p}" for p in table["id"]]
        table["generator"] = name
        table["family"] = families[name]
        truth.append(table.drop(columns=["id", "index"]))
    path = out / "sim" / "log.jsonl"
    atomic_write_text(path, "".join(line + "\n" for line in lines))
    df = pd.concat(truth, ignore_index=True)
    atomic_write_text(out / "sim" / "truth.csv", df.to_csv(index=False))
    return path, df


def fit(cfg: DictConfig, out: Path, log_path: Path) -> pd.DataFrame:
    """Fit the model space to the simulated log; ``fits.csv`` as a DataFrame."""
    from overhang_framework.config import compose_config
    from overhang_framework.fit.__main__ import run

    config = compose_config([], config_name="fit")
    for key in ("world", "value", "models", "depths", "states", "cache", "jobs", "progress"):
        config[key] = cfg[key]
    config.logs = [str(log_path)]
    config.out = str(out / "fit")
    config.pooled = False
    run(config)
    return pd.read_csv(out / "fit" / "fits.csv")


def _label(family: str, depth: int) -> str:
    return f"{family}/{'myopic' if depth == 1 else f'D{depth}'}"


def recovery_table(fits: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """One row per participant: the truth, the winning model, and the fit under the true model index."""
    from overhang_framework.fit.compare import per_participant

    df = per_participant(fits)
    rows = []
    for t in truth.itertuples(index=False):
        mine = df[df["participant"] == t.participant]
        if not len(mine):
            continue
        win = mine.loc[mine["bic"].idxmin()]
        family = mine[mine["family"] == t.family]
        best_depth = family.loc[family["bic"].idxmin()] if len(family) else None
        true_fit = family[family["depth"] == t.depth]
        true_fit = true_fit.iloc[0] if len(true_fit) else None
        rows.append({
            "participant": t.participant, "generator": t.generator, "true_family": t.family,
            "true_model": _label(t.family, int(t.depth)),
            "true_depth": int(t.depth), "true_sigma": _num(getattr(t, "sigma", None)), "true_beta": float(t.beta),
            "true_lapse": float(t.lapse), "winner": win["model"], "winner_family": win["family"],
            "winner_depth": int(win["depth"]),
            "fitted_depth": None if best_depth is None else int(best_depth["depth"]),
            "fitted_sigma": None if true_fit is None else _num(true_fit["sigma"]),
            "fitted_beta": None if true_fit is None else float(true_fit["beta"]),
            "fitted_lapse": None if true_fit is None else float(true_fit["lapse"]),
            "n": int(win["n"]),
            **{f"{k}_{axis}": _num(v) for axis in AXES for k, v in (
                ("true", getattr(t, axis, None)), ("fitted", None if true_fit is None else true_fit.get(axis)))},
        })
    return pd.DataFrame(rows)


def _num(value) -> Optional[float]:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def confusion(truth: Sequence[str], fitted: Sequence[str], labels: Sequence[str]) -> pd.DataFrame:
    """Counts: rows the generating label, columns the fitted one."""
    table = pd.crosstab(pd.Series(list(truth), name="generating"), pd.Series(list(fitted), name="fitted"))
    return table.reindex(index=labels, columns=labels, fill_value=0)


def correlation(x: Sequence[float], y: Sequence[float]) -> dict:
    """Pearson's r (and on log scales), the median absolute error and the median ratio fitted / true."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    out = {"n": int(len(x))}
    if len(x) >= 3 and np.std(x) > 0 and np.std(y) > 0:
        out["r"] = float(np.corrcoef(x, y)[0, 1])
        if (x > 0).all() and (y > 0).all():
            out["r_log"] = float(np.corrcoef(np.log(x), np.log(y))[0, 1])
    if len(x):
        out["median_abs_error"] = float(np.median(np.abs(y - x)))
        if (x > 0).all():
            out["median_ratio"] = float(np.median(y / x))
    return out


def drawn(table: pd.DataFrame, column: str) -> pd.Series:
    """Whether each participant's generator draws ``column`` (its participants' true values differ): a generator
    that holds a parameter fixed, and a model that fits it fixed, would count as recovered what was never
    estimated."""
    if column not in table:
        return pd.Series(False, index=table.index)
    groups = table.groupby("generator", dropna=False)[column]
    # a generator of one participant cannot show that it holds a parameter fixed: it counts
    varies = groups.transform(lambda values: values.nunique(dropna=True) > 1) | (groups.transform("size") == 1)
    return varies.fillna(False).astype(bool) & table[column].notna()


def _recovered(table: pd.DataFrame, name: str, mask: pd.Series) -> dict:
    """:func:`correlation` of ``true_<name>`` and ``fitted_<name>`` over the rows of ``mask``, with the generators
    of those rows."""
    out = correlation(table.loc[mask, f"true_{name}"], table.loc[mask, f"fitted_{name}"])
    out["generators"] = sorted(map(str, table.loc[mask, "generator"].unique()))
    return out


def summarise(table: pd.DataFrame, models: Sequence[str], bms_of: Optional[dict] = None) -> dict:
    """The headline figures of a recovery table (``bms_of``: :func:`bms_by_generator`'s, when computed). Each
    parameter's recovery counts the participants whose generator draws it (:func:`drawn`)."""
    family_ok = table["winner_family"] == table["true_family"]
    depth_ok = table["fitted_depth"] == table["true_depth"]
    has_sigma = drawn(table, "true_sigma") & table["fitted_sigma"].notna()
    summary = {
        "participants": int(len(table)),
        "depth_recovered": float(depth_ok.mean()) if len(table) else float("nan"),
        "family_recovered": float(family_ok.mean()) if len(table) else float("nan"),
        "model_recovered": float((table["winner"] == table["true_model"]).mean()) if len(table) else float("nan"),
        "by_generator": {g: {"participants": int(len(t)), "depth": float((t["fitted_depth"] == t["true_depth"]).mean()),
                             "family": float((t["winner_family"] == t["true_family"]).mean())}
                         for g, t in table.groupby("generator")},
        "sigma": _recovered(table, "sigma", has_sigma),
        "beta": _recovered(table, "beta", drawn(table, "true_beta")),
        "lapse": _recovered(table, "lapse", drawn(table, "true_lapse")),
        "models": list(models),
    }
    for axis in AXES:
        both = drawn(table, f"true_{axis}") & table[f"fitted_{axis}"].notna() if f"true_{axis}" in table else []
        if len(table) and f"true_{axis}" in table and both.any():
            summary[axis] = _recovered(table, axis, both)
            summary[axis]["median_bias"] = float(np.median(table.loc[both, f"fitted_{axis}"]
                                                           - table.loc[both, f"true_{axis}"]))
    if bms_of is not None:
        summary["bms"] = bms_of
    summary["targets"] = {
        "depth": {"target": TARGETS["depth"], "value": summary["depth_recovered"],
                  "met": bool(summary["depth_recovered"] >= TARGETS["depth"])},
        "family": {"target": TARGETS["family"], "value": summary["family_recovered"],
                   "met": bool(summary["family_recovered"] >= TARGETS["family"])},
    }
    if "r" in summary["sigma"]:
        summary["targets"]["sigma_r"] = {"target": TARGETS["sigma_r"], "value": summary["sigma"]["r"],
                                         "met": bool(summary["sigma"]["r"] >= TARGETS["sigma_r"])}
    return summary


def bms_by_generator(fits: pd.DataFrame, truth: pd.DataFrame) -> dict:
    """Each generator's participants alone, compared by random-effects BMS over the fitted models (log evidence
    ``-BIC / 2``): the model frequencies' most frequent model, its protected exceedance probability, and the
    Bayesian omnibus risk."""
    from overhang_framework.fit.bms import bms
    from overhang_framework.fit.compare import per_participant

    df = per_participant(fits)
    out = {}
    for generator, group in truth.groupby("generator", sort=False):
        mine = df[df["participant"].isin(set(group["participant"]))]
        wide = mine.pivot_table(index="participant", columns="model", values="bic", aggfunc="first").dropna()
        if len(wide) < 2 or wide.shape[1] < 2:
            continue
        result = bms(-wide.to_numpy(dtype=float) / 2)
        pxp = np.asarray(result.pxp, dtype=float)
        best = int(np.argmax(pxp))
        out[str(generator)] = {"participants": int(len(wide)), "model": str(wide.columns[best]),
                               "pxp": float(pxp[best]), "bor": float(result.bor),
                               "frequency": float(np.asarray(result.frequencies, dtype=float)[best])}
    return out


def _matrix_md(matrix: pd.DataFrame) -> str:
    from overhang_framework.behaviour.analysis import markdown_table

    header = ["generating \\ fitted"] + [str(c) for c in matrix.columns]
    rows = [[str(i)] + [int(v) for v in matrix.loc[i]] for i in matrix.index]
    return markdown_table(header, rows)


def _fmt(value, digits: int = 3) -> str:
    return "–" if value is None or (isinstance(value, float) and not math.isfinite(value)) else f"{value:.{digits}f}"


def report(table: pd.DataFrame, summary: dict, out: Path) -> str:
    """Write ``recovery.md``, ``recovery.csv``, ``recovery.json`` and ``recovery.png``; return the markdown."""
    from overhang_framework.behaviour.analysis import markdown_table

    models = summary["models"]
    model_matrix = confusion(table["true_model"], table["winner"], models)
    depths = sorted(set(table["true_depth"]) | set(table["fitted_depth"].dropna().astype(int)))
    depth_matrix = confusion(table["true_depth"], table["fitted_depth"].astype("Int64"), depths)
    lines = ["# Parameter and model recovery", "",
             f"{summary['participants']} simulated participants of known models and parameters, fitted with the "
             f"model space {', '.join(models)} (winner: lowest BIC).", "", "## Targets", ""]
    rows = [[name, f"{t['value']:.2f}" if name == "sigma_r" else f"{t['value']:.0%}",
             f"≥ {t['target']:.2f}" if name == "sigma_r" else f"≥ {t['target']:.0%}", "met" if t["met"] else "not met"]
            for name, t in summary["targets"].items()]
    names = {"depth": "depth recovered (within the generating family)",
             "family": "generating predictor family wins", "sigma_r": "r(true σ, fitted σ)"}
    lines += [markdown_table(["what", "value", "target", ""], [[names[r[0]]] + r[1:] for r in rows]), ""]
    lines += ["## By generating model", "",
              markdown_table(["generator", "participants", "depth recovered", "family wins"],
                             [[g, v["participants"], f"{v['depth']:.0%}", f"{v['family']:.0%}"]
                              for g, v in summary["by_generator"].items()]), ""]
    lines += ["## Parameters under the generating model index", "",
              "Each over the participants whose generator draws it (a parameter none draws is left out).", "",
              markdown_table(["parameter", "n", "r", "r (log)", "median abs. error", "median fitted / true",
                              "generators"],
                             [[p, summary[p]["n"], _fmt(summary[p].get("r")), _fmt(summary[p].get("r_log")),
                               _fmt(summary[p].get("median_abs_error"), 4), _fmt(summary[p].get("median_ratio")),
                               ", ".join(summary[p].get("generators", []))]
                              for p in ("sigma", "beta", "lapse") if summary[p]["n"]]), ""]
    axes = [a for a in AXES if a in summary]
    if axes:
        lines += ["## The new axes under the generating model index (on their grids)", "",
                  markdown_table(["parameter", "n", "r", "median abs. error", "median bias (fitted - true)",
                                  "generators"],
                                 [[a, summary[a]["n"], _fmt(summary[a].get("r")),
                                   _fmt(summary[a].get("median_abs_error"), 4), _fmt(summary[a].get("median_bias"), 4),
                                   ", ".join(summary[a].get("generators", []))]
                                  for a in axes]), ""]
    if summary.get("bms"):
        lines += ["## Each generator's participants compared by random-effects BMS", "",
                  markdown_table(["generator", "participants", "most frequent model", "its frequency", "its PXP",
                                  "omnibus risk"],
                                 [[g, v["participants"], v["model"], _fmt(v["frequency"], 2), _fmt(v["pxp"], 2),
                                   _fmt(v["bor"], 3)] for g, v in summary["bms"].items()]), ""]
    lines += ["## Depth: generating against fitted (within the generating family)", "", _matrix_md(depth_matrix), ""]
    lines += ["## Model: generating against winning", "", _matrix_md(model_matrix), "",
              "Off-diagonal cells are models the data cannot tell apart at this size: the winning model "
              "predicts the generating model's actions about as well, with no more parameters.", "",
              "![recovery](recovery.png)", ""]
    text = "\n".join(lines)
    atomic_write_text(out / "recovery.md", text)
    atomic_write_text(out / "recovery.csv", table.to_csv(index=False))
    atomic_write_json(out / "recovery.json", summary)
    _figure(table, model_matrix, depth_matrix, out / "recovery.png")
    return text


def _figure(table: pd.DataFrame, model_matrix: pd.DataFrame, depth_matrix: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    from overhang_framework.behaviour.analysis import save_figure

    fig, axes = plt.subplots(2, 2, figsize=(10, 9))
    for ax, name, scale in ((axes[0, 0], "sigma", "log"), (axes[0, 1], "beta", "log")):
        t = table[drawn(table, f"true_{name}") & table[f"fitted_{name}"].notna()]
        x, y = t[f"true_{name}"].to_numpy(float), t[f"fitted_{name}"].to_numpy(float)
        for g, part in t.groupby("generator"):
            ax.scatter(part[f"true_{name}"], part[f"fitted_{name}"].clip(lower=1e-3), s=18, label=g, alpha=0.8)
        if len(x):
            lo, hi = max(min(x.min(), y[y > 0].min() if (y > 0).any() else x.min()), 1e-3), max(x.max(), y.max())
            ax.plot([lo, hi], [lo, hi], color="grey", lw=1, ls="--")
            ax.set_xscale(scale)
            ax.set_yscale(scale)
            for axis in (ax.xaxis, ax.yaxis):  # plain numbers at 1, 2 and 5 of each decade, no crowded minor labels
                axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
                axis.set_major_formatter(FormatStrFormatter("%g"))
                axis.set_minor_formatter(NullFormatter())
            ax.legend(fontsize=8)
        ax.set_xlabel(f"true {name}")
        ax.set_ylabel(f"fitted {name} (generating model index)")
        ax.set_title(f"{name} recovery")
    for ax, matrix, title in ((axes[1, 0], depth_matrix, "depth (within the generating family)"),
                              (axes[1, 1], model_matrix, "model: generating vs winning (BIC)")):
        values = matrix.to_numpy(dtype=float)
        shares = values / np.maximum(values.sum(axis=1, keepdims=True), 1)
        ax.imshow(shares, cmap="Blues", vmin=0, vmax=1)
        ax.set_xticks(range(len(matrix.columns)), [str(c) for c in matrix.columns], rotation=45, ha="right",
                      fontsize=8)
        ax.set_yticks(range(len(matrix.index)), [str(i) for i in matrix.index], fontsize=8)
        for i in range(values.shape[0]):
            for j in range(values.shape[1]):
                if values[i, j]:
                    ax.text(j, i, int(values[i, j]), ha="center", va="center",
                            color="white" if shares[i, j] > 0.5 else "black", fontsize=8)
        ax.set_xlabel("fitted")
        ax.set_ylabel("generating")
        ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)


def run(cfg: DictConfig) -> dict:
    checked = check_config(cfg)
    out, space = checked["out"], checked["space"]
    out.mkdir(parents=True, exist_ok=True)
    log_path, truth = simulate(cfg, out, checked["generators"], checked["families"])
    fits = fit(cfg, out, log_path)
    table = recovery_table(fits, truth)
    summary = summarise(table, [index.label for index in space], bms_by_generator(fits, truth))
    report(table, summary, out)
    return summary


def checked_config(args: Sequence[str]) -> DictConfig:
    """The recovery config of the command line ``args`` (``--out DIR``, ``--config-name NAME``, overrides), composed and
    checked (nothing simulated or fitted); one :class:`OverhangError` line otherwise."""
    from overhang_framework.preflight import check_flags, compose_checked, split_flags

    words, out, name = [], None, CONFIG_NAME
    it = iter(args)
    for word in it:
        if word == "--out":
            out = next(it, None)
        elif word.startswith("--out="):
            out = word.split("=", 1)[1]
        elif word in ("--config-name", "-cn"):
            name = next(it, None) or ""
        elif word.startswith("--config-name="):
            name = word.split("=", 1)[1]
        else:
            words.append(word)
    check_flags(words)
    flags, overrides = split_flags(words)
    if flags:
        raise ConfigError(f"recovery takes overrides only, not {' '.join(flags)}")
    if out is not None:
        overrides.append(f"out='{Path(out).resolve()}'")
    if name not in CONFIGS:
        raise ConfigError(f"--config-name {name!r} is not a recovery config; allowed: {', '.join(CONFIGS)}")
    cfg = compose_checked(overrides, config_name=name)
    check_config(cfg)
    return cfg


def main(argv: Optional[Sequence[str]] = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    if "--help" in args or "-h" in args:
        print(__doc__)
        return
    try:
        cfg = checked_config(args)
        Path(cfg.out).mkdir(parents=True, exist_ok=True)
        logging.basicConfig(filename=str(Path(cfg.out) / "recovery.log"), level=logging.INFO,
                            format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
        summary = run(cfg)
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted: run the same command to continue (simulations from their parts, the fit from the "
              "score cache)", file=sys.stderr)
        sys.exit(130)
    targets = ", ".join(f"{k} {v['value']:.2f} ({'met' if v['met'] else 'not met'})"
                        for k, v in summary["targets"].items())
    print(f"{summary['participants']} participants: {targets}")
    print(f"wrote {Path(cfg.out) / 'recovery.md'}")


if __name__ == "__main__":
    main()
