"""Physical prediction by construction stage (the paper's Fig. 4).

Every executed placement is a positive sample of perceived plausibility: for each, each predictor
gives the probability that the tower stands after it, and its log-likelihood is
``log(clip(p, ε, 1 − ε))``. Timed-out records place nothing and are skipped. Predictors are asked with
the logged (continuous) ``x``, all placements made from one state (same tower, same remaining blocks)
in one batch, and the distinct states of the whole log in one ``predict_many`` call per predictor,
each state with its own generator seeded from the seed and the state's canonical key (so the IPE's
noise does not depend on what else is in the log).

By construction stage: the number of blocks in the tower after the placement (the tower being judged;
2 = the first placement on the ground block). The mean over a group's placements at that stage, with a
95% CI by bootstrap over participants (participants resampled with replacement; the pooled mean of
their placements). The IPE's advantage over the CNN relative to the veridical baseline is
``(LL_ipe − LL_vrd) − (LL_cnn − LL_vrd)`` per placement.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.analysis import (Section, bootstrap_ci, colour, markdown_table, save_figure,
                                                   write_csv)
from overhang_framework.geometry import Action, Block, Geometry, check_width
from overhang_framework.interfaces import State

ADVANTAGE = ("ipe", "cnn", "veridical")
LABELS = {"veridical": "veridical", "ipe": "IPE", "cnn": "visual heuristic (CNN)", "hybrid": "hybrid"}


def build_predictors(names: Sequence[str], world, overrides: Sequence[str] = ()) -> dict:
    """Each named predictor, built through the plugin registry from its config (as the main job builds it),
    on ``world``."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.plugins import Registry

    registry = Registry()
    known = registry.names("predictor")
    unknown = [n for n in names if n not in known]
    if unknown:
        from overhang_framework.errors import OverhangError

        raise OverhangError(f"--predictors: unknown predictor {', '.join(map(repr, unknown))}; "
                            f"installed predictors: {', '.join(sorted(known))}")
    out = {}
    for name in names:
        cfg = compose_config([*overrides, f"predictor={name}"])
        out[name] = registry.create("predictor", OmegaConf.to_container(cfg.predictor, resolve=True), world=world)
    return out


def state_seed(seed: int, key: tuple) -> int:
    """A generator seed from the analysis seed and a state's canonical key (stable across runs and logs)."""
    return int.from_bytes(hashlib.sha256(repr((seed, key)).encode()).digest()[:8], "little")


def placements(df: pd.DataFrame) -> pd.DataFrame:
    """The executed placements (timed-out records left out) with ``n_blocks`` (after the placement)."""
    done = df[~df["timed_out"]].copy()
    done["n_blocks"] = done["tower_before"].map(len) + 1
    return done


def probabilities(done: pd.DataFrame, predictors: dict, seed: int) -> dict[str, np.ndarray]:
    """Each predictor's probability for every row of ``done``: one request per distinct state, all in one call."""
    states: dict[tuple, tuple[State, dict]] = {}
    index = []
    for before, seq, step, x, layer in zip(done["tower_before"], done["sequence"], done["step"], done["x"],
                                           done["layer"]):
        geometry = Geometry(tuple(Block(check_width(w), float(bx), int(bl)) for w, bx, bl in before))
        remaining = tuple(float(w) for w in seq[step:])
        key = (geometry.key, tuple(round(w, 6) for w in remaining))
        if key not in states:
            states[key] = (State(geometry, remaining), {})
        actions = states[key][1]
        action = Action(float(x), int(layer))
        actions.setdefault(action, len(actions))
        index.append((key, actions[action]))
    keys = list(states)
    requests = [(states[k][0], list(states[k][1])) for k in keys]
    position = {k: i for i, k in enumerate(keys)}
    out = {}
    for name, predictor in predictors.items():
        rngs = [np.random.default_rng(state_seed(seed, k)) for k in keys]
        answers = predictor.predict_many(requests, rngs)
        out[name] = np.array([float(answers[position[k]][j]) for k, j in index], dtype=float)
    return out


def log_likelihoods(p: np.ndarray, epsilon: float) -> np.ndarray:
    return np.log(np.clip(p, epsilon, 1 - epsilon))


def by_stage(done: pd.DataFrame, values: dict[str, np.ndarray], order: Sequence[str], n_boot: int,
             seed: int) -> pd.DataFrame:
    """Mean of each value column by group and ``n_blocks``, with its bootstrap CI over participants."""
    rows = []
    frame = done[["group", "participant", "n_blocks"]].copy()
    for name, v in values.items():
        frame[name] = v
    for g in order:
        sub = frame[frame["group"] == g]
        for n in sorted(sub["n_blocks"].unique()):
            at = sub[sub["n_blocks"] == n]
            for name in values:
                per = at.groupby("participant")[name].agg(["sum", "count"])
                lo, hi = bootstrap_ci(per["sum"].to_numpy(), per["count"].to_numpy(), n_boot, seed)
                rows.append({"group": g, "n_blocks": int(n), "measure": name, "placements": len(at),
                             "participants": len(per), "mean": float(at[name].mean()), "ci_low": lo, "ci_high": hi})
    return pd.DataFrame(rows)


def sign_change(stage: pd.DataFrame, group: str) -> Optional[int]:
    """The first stage (number of blocks) at which the mean advantage has the other sign than at the stage before."""
    adv = stage[(stage["group"] == group) & (stage["measure"] == "advantage")].sort_values("n_blocks")
    signs = np.sign(adv["mean"].to_numpy())
    for i in range(1, len(signs)):
        if signs[i] != 0 and signs[i - 1] != 0 and signs[i] != signs[i - 1]:
            return int(adv["n_blocks"].iloc[i])
    return None


def figure(stage: pd.DataFrame, order: Sequence[str], names: Sequence[str], epsilon: float, n_boot: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import MaxNLocator

    has_adv = (stage["measure"] == "advantage").any()
    groups = [g for g in order if (stage["group"] == g).any()]
    fig, axes = plt.subplots(len(groups), 2 if has_adv else 1, figsize=(10 if has_adv else 5.5, 3.2 * len(groups)),
                             squeeze=False)
    pcol = {"veridical": "#555555", "ipe": "#2f6db5", "cnn": "#d0452f", "hybrid": "#3a9a5b"}
    extra = iter(["#8e5bb5", "#b5875b", "#2aa3a3", "#c2559a"])
    for r, g in enumerate(groups):
        ax = axes[r][0]
        for name in names:
            d = stage[(stage["group"] == g) & (stage["measure"] == name)].sort_values("n_blocks")
            c = pcol.get(name) or next(extra, "#000000")
            ax.plot(d["n_blocks"], d["mean"], "o-", color=c, label=LABELS.get(name, name))
            ax.fill_between(d["n_blocks"], d["ci_low"], d["ci_high"], color=c, alpha=0.2)
        ax.set_ylabel(f"{g}\nmean log-likelihood")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("blocks in the scene (after the placement)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        if r == 0:
            ax.set_title(f"log-likelihood of executed placements (ε = {epsilon:g}; 95% CI)", fontsize=9)
        if has_adv:
            ax = axes[r][1]
            d = stage[(stage["group"] == g) & (stage["measure"] == "advantage")].sort_values("n_blocks")
            ax.axhline(0, color="black", lw=0.8)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.plot(d["n_blocks"], d["mean"], "o-", color=colour(g, order))
            ax.fill_between(d["n_blocks"], d["ci_low"], d["ci_high"], color=colour(g, order), alpha=0.2)
            flip = sign_change(stage, g)
            if flip is not None:
                ax.axvline(flip - 0.5, color="grey", ls="--", lw=0.8)
                ax.text(0.02, 0.04, f"sign changes at {flip} blocks", transform=ax.transAxes, fontsize=8,
                        color="dimgrey")
            ax.set_xlabel("blocks in the scene (after the placement)")
            ax.set_ylabel("IPE advantage over CNN\n(LL_ipe − LL_vrd) − (LL_cnn − LL_vrd)")
            ax.grid(alpha=0.3)
            if r == 0:
                ax.set_title(f"> 0: IPE fits better; < 0: CNN fits better ({n_boot} bootstrap resamples)", fontsize=9)
    fig.tight_layout()
    return fig


def section(df: pd.DataFrame, out: Path, order, compare, settings, world) -> Section:
    done = placements(df)
    skipped = int(df["timed_out"].sum())
    names = list(settings.predictors)
    predictors = build_predictors(names, world, settings.world_overrides)
    probs = probabilities(done, predictors, settings.seed)
    values = {n: log_likelihoods(p, settings.epsilon) for n, p in probs.items()}
    if all(n in values for n in ADVANTAGE):
        values["advantage"] = ((values["ipe"] - values["veridical"]) - (values["cnn"] - values["veridical"]))
    stage = by_stage(done, values, order, settings.bootstrap, settings.seed)
    per = done[["participant", "group", "task_id", "trial", "step", "n_blocks", "x", "layer", "stable"]].copy()
    for n, p in probs.items():
        per[f"p_{n}"] = p
        per[f"ll_{n}"] = values[n]
    write_csv(per, out / "fig4_placements.csv")
    write_csv(stage, out / "fig4_loglik.csv")
    files = ["fig4_loglik.csv", "fig4_placements.csv"]
    overall = []
    for g in order:
        at = per[per["group"] == g]
        if not len(at):
            continue
        row = [g, len(at)] + [f"{at[f'll_{n}'].mean():.3f}" for n in names]
        if "advantage" in values:
            flip = sign_change(stage, g)
            row.append("none" if flip is None else f"{flip} blocks")
        overall.append(row)
    header = ["group", "placements"] + [f"mean LL {n}" for n in names]
    if "advantage" in values:
        header.append("IPE − CNN advantage changes sign at")
    text = markdown_table(header, overall)
    text += (f"\n\nRules: every executed placement is a positive sample; LL = log(clip(p, ε, 1 − ε)) with ε = "
             f"{settings.epsilon:g}; predictors asked with the logged continuous x, one batch per distinct state, "
             f"each state's generator seeded from seed {settings.seed} and its canonical key; stage = blocks in the "
             f"tower after the placement; 95% CIs by bootstrap over participants ({settings.bootstrap} resamples, "
             f"percentile). Timed-out records skipped: {skipped}. Distinct states asked: "
             f"{len(set(zip(done['participant'], done['trial'], done['step'])))} placements in "
             f"{_distinct_states(done)} states.")
    if "advantage" not in values:
        text += " The IPE − CNN advantage needs the predictors veridical, ipe and cnn."
    if len(stage):
        save_figure(figure(stage, order, names, settings.epsilon, settings.bootstrap), out / "fig4_loglik.png")
        files.insert(1, "fig4_loglik.png")
    else:
        text += "\n\nNo executed placement: no figure."
    return Section("Physical prediction by construction stage (Fig. 4)", text, files)


def _distinct_states(done: pd.DataFrame) -> int:
    return len({(tuple(map(tuple, b)), tuple(s[k:])) for b, s, k in
                zip(done["tower_before"], done["sequence"], done["step"])})
