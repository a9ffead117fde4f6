"""Held-out likelihood (fit ... cv=K): folds of each participant's trials, and the fit's held-out scores."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from overhang_framework.fit.fitting import fold_of


def test_folds_are_disjoint_cover_every_trial_keep_trials_whole_and_ignore_order():
    rng = np.random.default_rng(1)
    trials = [(f"p{p}", t) for p in range(5) for t in range(1, 21) for _ in range(int(rng.integers(1, 6)))]
    fold = fold_of(trials, 5)
    assert fold.min() == 0 and fold.max() == 4
    by_trial = {}
    for key, k in zip(trials, fold):
        by_trial.setdefault(key, set()).add(int(k))
    assert all(len(ks) == 1 for ks in by_trial.values())  # a trial's placements share one fold
    # every participant's 20 trials are dealt 4 to each fold: disjoint folds that cover every trial
    for p in range(5):
        counts = np.bincount([next(iter(ks)) for (pid, _), ks in by_trial.items() if pid == f"p{p}"], minlength=5)
        assert counts.tolist() == [4, 4, 4, 4, 4]
    shuffled = [trials[i] for i in rng.permutation(len(trials))]
    again = dict(zip(shuffled, fold_of(shuffled, 5)))
    assert all(again[key] == k for key, k in zip(trials, fold))
    # a participant's folds do not depend on who else is fitted with them (a pooled fit)
    alone = [key for key in trials if key[0] == "p2"]
    assert (fold_of(alone, 5) == fold[[key[0] == "p2" for key in trials]]).all()
    assert not (fold_of(trials, 5, seed=1) == fold).all()


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    from search_fixtures import simulated_log

    return simulated_log(tmp_path_factory.mktemp("cv"),
                         "[[1.2,0.6,1.2],[0.6,1.2,0.6,0.6],[1.8,0.6,0.6],[1.2,1.2,0.6]]")


def test_a_cross_validated_fit_scores_every_fold_with_parameters_fitted_on_the_others(tmp_path, small_log):
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.fit.fitting import _decisions, _subset, fit_softmax, log_placements, map_placements
    from overhang_framework.fit.likelihood import log_likelihood
    from overhang_framework.fit.scores import Model, ScoreCache, ScoreTables
    from overhang_framework.plugins import Registry

    cache = tmp_path / "scores.sqlite"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(small_log), "--out", str(tmp_path / "fit"),
                           "world.physics=static", "~models.cnn", "~models.hybrid", "models.ipe.K=10",
                           "models.ipe.sigma=[0.02,0.08]", "+models.veridical={predictor: veridical}",
                           "depths=[1,2]", "cv=2", f"cache={cache}",
                           "progress=false"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(tmp_path / "fit" / "fits.csv")
    assert fits["heldout_loglik"].notna().all() and (fits["folds"] == 2).all()
    assert (fits["heldout_loglik"] < 0).all()
    text = (tmp_path / "fit" / "comparison.md").read_text()
    assert "**Held-out likelihood** (2 folds" in text and "Σ held-out LL" in text
    # one participant by hand: fit beta and lapse on each fold's complement, score the fold
    pid = "sim-un-001"
    row = fits[(fits["participant"] == pid) & (fits["model"] == "veridical/myopic")].iloc[0]
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config

    registry = Registry()
    cfg = OmegaConf.to_container(compose_config(["world.physics=static"], config_name="fit"), resolve=True)
    context = {"world": cfg["world"], "value": cfg["value"]}  # as the fit keys its tables
    world = registry.create("world", dict(context["world"]))
    value = registry.create("value", dict(context["value"]), world=world)
    model = Model(OmegaConf.to_container(compose_config(["predictor=veridical"]).predictor, resolve=True), 1,
                  "veridical")
    tables = ScoreTables(world, value, registry.create("predictor", dict(model.predictor), world=world), model,
                         context, ScoreCache(cache))
    placements = [p for p in log_placements(read_log(small_log)) if p.participant == pid]
    mapped = map_placements(world, placements)
    fold = fold_of(mapped.trials, 2)
    every = _decisions(tables, mapped)
    total = 0.0
    for k in range(2):
        train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
        fit = fit_softmax(_subset(every, train))
        total += log_likelihood(_subset(every, test), fit.beta, fit.lapse)
    assert tables.stats.computed == 0  # the fit's own tables, from its cache
    assert row["heldout_loglik"] == pytest.approx(total)
    # a sigma grid: each fold picks its own grid point on the other fold
    ipe = fits[(fits["participant"] == pid) & (fits["model"] == "ipe/myopic")].iloc[0]
    base = OmegaConf.to_container(compose_config(["predictor=ipe"]).predictor, resolve=True)
    grid = [ScoreTables(world, value, registry.create("predictor", {**base, "K": 10, "sigma": s}, world=world),
                        Model({**base, "K": 10, "sigma": s}, 1, "ipe"), context, ScoreCache(cache))
            for s in (0.02, 0.08)]
    decisions = [_decisions(t, mapped) for t in grid]
    total = 0.0
    for k in range(2):
        train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
        fits_k = [fit_softmax(_subset(d, train)) for d in decisions]
        best = int(np.argmax([f.loglik for f in fits_k]))
        total += log_likelihood(_subset(decisions[best], test), fits_k[best].beta, fits_k[best].lapse)
    assert sum(t.stats.computed for t in grid) == 0 and ipe["k"] == 3
    assert ipe["heldout_loglik"] == pytest.approx(total)


def test_cv_must_be_0_or_at_least_2_folds(tmp_path, small_log):
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(small_log), "--out", str(tmp_path / "f"),
                           "cv=1"], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "cv must be 0 (no cross-validation) or a number of folds >= 2, got 1" in proc.stderr


def test_a_participant_whose_placements_all_fall_in_one_fold_has_no_held_out_score():
    from overhang_framework.fit.fitting import Mapped, heldout_loglik
    from overhang_framework.fit.scores import Model, ScoreTables
    from overhang_framework.geometry import Block, Geometry
    from overhang_framework.interfaces import State
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    value = registry.create("value", {"name": "overhang"}, world=world)
    model = Model({"name": "veridical"}, 1)
    tables = ScoreTables(world, value, registry.create("predictor", {"name": "veridical"}, world=world), model,
                         {"world": {}, "value": {}})
    state = State(Geometry((Block(1.2, 0.0, 0),)), (0.6, 1.2))
    one_trial = Mapped([state, state], [0, 1], 0, [("p", 1), ("p", 1)])
    assert np.isnan(heldout_loglik([tables], one_trial, 2))
    two_trials = Mapped([state, state], [0, 1], 0, [("p", 1), ("p", 2)])
    assert np.isfinite(heldout_loglik([tables], two_trials, 2))
