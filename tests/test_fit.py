"""Model fitting (python -m overhang_framework.fit): likelihood, score tables and their cache, BMS, errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from overhang_framework.fit.bms import bms
from overhang_framework.fit.likelihood import Decisions, action_index, choice_probabilities, log_likelihood
from overhang_framework.fit.scores import Model, ScoreCache, ScoreTables
from overhang_framework.geometry import Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import Registry

CONTEXT = {"world": {"name": "overhang", "physics": "static"}, "value": {"name": "overhang"}}


@pytest.fixture(scope="module")
def world():
    return Registry().create("world", CONTEXT["world"])


@pytest.fixture(scope="module")
def value(world):
    return Registry().create("value", CONTEXT["value"], world=world)


def tables(world, value, predictor: dict, depth: int, cache=None) -> ScoreTables:
    model = Model(predictor, depth)
    built = Registry().create("predictor", dict(predictor), world=world)
    return ScoreTables(world, value, built, model, CONTEXT, cache)


def state(blocks, remaining) -> State:
    return State(Geometry(tuple(Block(float(w), float(x), int(layer)) for w, x, layer in blocks)),
                 tuple(float(w) for w in remaining))


# a 1.2 ground block and a 0.6 block to place, then a 1.2 one
FIRST = state([[1.2, 0.0, 0]], [0.6, 1.2])
SECOND = state([[1.2, 0.0, 0], [0.6, 0.4, 1]], [1.2])


def test_the_likelihood_of_a_hand_built_state_is_the_hand_computed_softmax(world, value):
    actions = world.legal_actions(FIRST)
    scores = tables(world, value, {"name": "veridical"}, 1).table(FIRST)
    # by hand: the myopic score is 1{stands} * overhang after the placement, overhang = max(0.6, |x| + 0.3)
    by_hand = []
    for a in actions:
        after = world.step(FIRST, a).geometry
        reach = max(0.6, abs(a.x) + 0.3) if a.layer == 1 else max(0.6, abs(a.x) + 0.3)
        by_hand.append(reach if world.is_stable(after) else 0.0)
    assert scores == pytest.approx(by_hand)
    beta, lapse = 7.0, 0.1
    chosen = action_index(world, FIRST, 0.42, 1)
    assert actions[chosen].x == pytest.approx(0.4) and actions[chosen].layer == 1
    weights = [math.exp(beta * s) for s in by_hand]
    p = (1 - lapse) * weights[chosen] / sum(weights) + lapse / len(actions)
    d = Decisions.of([scores], [chosen])
    assert log_likelihood(d, beta, lapse) == pytest.approx(math.log(p), rel=1e-12)
    assert choice_probabilities(scores, beta, lapse)[chosen] == pytest.approx(p, rel=1e-12)
    assert choice_probabilities(scores, beta, lapse).sum() == pytest.approx(1.0)
    # two decisions of different sizes: the sum of their log-probabilities
    s2 = tables(world, value, {"name": "veridical"}, 1).table(SECOND)
    c2 = action_index(world, SECOND, 0.1, 2)
    both = Decisions.of([scores, s2], [chosen, c2])
    assert log_likelihood(both, beta, lapse) == pytest.approx(
        math.log(p) + math.log(choice_probabilities(s2, beta, lapse)[c2]), rel=1e-12)


def test_a_placement_maps_to_the_nearest_legal_grid_action_of_its_layer_or_to_none(world):
    actions = world.legal_actions(FIRST)
    i = action_index(world, FIRST, -0.26, 1)
    assert (actions[i].x, actions[i].layer) == (pytest.approx(-0.3), 1)
    assert action_index(world, FIRST, 0.0, 2) is None        # no legal action on layer 2 yet
    assert action_index(world, FIRST, 3.9, 1) is None        # more than a grid step from any legal action


def test_a_cached_table_equals_a_fresh_one_and_tables_do_not_depend_on_what_was_asked_before(tmp_path, world, value):
    ipe = {"name": "ipe", "K": 10, "sigma": 0.04, "backend": "static"}
    cache = ScoreCache(tmp_path / "scores.sqlite")
    first = tables(world, value, ipe, 2, cache)
    a, b = first.table(FIRST), first.table(SECOND)
    assert first.stats.computed == 2 and len(cache) == 2
    cache.close()
    again = ScoreCache(tmp_path / "scores.sqlite")
    warm = tables(world, value, ipe, 2, again)
    assert np.array_equal(warm.table(SECOND), b) and np.array_equal(warm.table(FIRST), a)
    assert warm.stats.computed == 0 and warm.stats.cached == 2
    fresh = tables(world, value, ipe, 2)             # no cache, the other order
    assert np.array_equal(fresh.table(SECOND), b) and np.array_equal(fresh.table(FIRST), a)
    # another sigma is another table, with the same draws (common random numbers), and a cache miss
    other = tables(world, value, {**ipe, "sigma": 0.08}, 2, again)
    assert not np.array_equal(other.table(FIRST), a) and other.stats.computed == 1
    assert Model(ipe, 2).draw_seed(CONTEXT) == Model({**ipe, "sigma": 0.08}, 2).draw_seed(CONTEXT)
    assert Model(ipe, 2).key(CONTEXT) != Model({**ipe, "sigma": 0.08}, 2).key(CONTEXT)


def test_bms_equals_groupbmc_on_known_evidence():
    groupbmc = pytest.importorskip("groupBMC.groupBMC")
    rng = np.random.default_rng(3)
    for shift in ([0.0, 1.5, 0.5], [0.0, 0.0, 4.0]):
        L = rng.normal(size=(20, 3)) * 3 + np.array(shift)
        ref = groupbmc.GroupBMC(L.T, max_iter=10_000, tolerance=1e-12).get_result()   # its prior: alpha0 = 1/K
        ours = bms(L, alpha0=1 / 3, samples=2_000_000)
        assert ours.frequencies == pytest.approx(ref.frequency_mean, abs=1e-6)
        # exceedance probabilities by 2,000,000 Dirichlet samples: within 5 standard errors
        assert ours.ep == pytest.approx(ref.exceedance_probability, abs=5 * 0.5 / math.sqrt(2_000_000))
        assert ours.pxp == pytest.approx(ref.protected_exceedance_probability, abs=2e-3)
        ref1 = groupbmc.GroupBMC(L.T, np.ones(3), max_iter=10_000, tolerance=1e-12).get_result()
        assert bms(L).frequencies == pytest.approx(ref1.frequency_mean, abs=1e-6)
    # identical evidence: nothing to choose, the omnibus risk is near 1 and every PXP near 1/K
    flat = bms(np.zeros((30, 4)))
    assert flat.bor > 0.95 and flat.pxp == pytest.approx([0.25] * 4, abs=0.01)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "overhang_framework.fit", *args], capture_output=True, text=True)


def test_a_malformed_or_unusable_log_fails_with_one_line(tmp_path):
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"log_version": 1, "participant": "p"}\n')
    proc = _cli(str(bad), "--out", str(tmp_path / "out"))
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1, proc.stderr
    assert "bad.jsonl" in proc.stderr and "line 1" in proc.stderr
    proc = _cli(str(tmp_path / "missing.jsonl"), "--out", str(tmp_path / "out"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "missing.jsonl" in proc.stderr, proc.stderr
    proc = _cli(str(bad))
    assert proc.returncode == 2 and "--out" in proc.stderr
    proc = _cli(str(bad), "--out", str(tmp_path / "out"), "depths=[1,9]")
    assert proc.returncode == 2 and "fit.depths: 9 is not a depth" in proc.stderr, proc.stderr
    proc = _cli(str(bad), "--out", str(tmp_path / "out"), "+models.magic={predictor: crystal_ball}")
    assert proc.returncode == 2 and "unknown predictor 'crystal_ball'" in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory):
    """A simulated log: 2 + 2 participants, three short tasks, static physics."""
    from overhang_framework.config import compose_config
    from overhang_framework.participants import CONFIG_NAME, run

    out = tmp_path_factory.mktemp("sim")
    run(compose_config(["tasks=custom", "tasks.sequences=[[1.2,0.6,1.2],[0.6,1.2,0.6,0.6],[1.8,0.6,0.6]]",
                        "world.physics=static", "predictor.K=10", "progress=false",
                        "cohort.participants.time_limited=2", "cohort.participants.unconstrained=2",
                        "cohort.n_tasks=null"], config_name=CONFIG_NAME), out)
    return out / "log.jsonl"


FIT = ["world.physics=static", "~models.cnn", "~models.hybrid", "models.ipe.K=10", "models.ipe.sigma=[0.02,0.06]",
       "+models.veridical={predictor: veridical}", "progress=false"]


def test_a_fit_writes_every_participant_x_model_and_shards_give_the_same_fits(tmp_path, tiny_log):
    one = tmp_path / "one"
    proc = _cli(str(tiny_log), "--out", str(one), *FIT, f"cache={tmp_path / 'scores.sqlite'}")
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(one / "fits.csv")
    models = {"ipe/myopic", "ipe/D2", "veridical/myopic", "veridical/D2"}
    assert set(fits["model"]) == models
    assert len(fits) == len(models) * (4 + 2)               # 4 participants and 2 pooled conditions
    assert set(fits.loc[fits["family"] == "ipe", "sigma"]) <= {0.02, 0.06} and fits["k"].isin([2, 3]).all()
    row = fits.iloc[0]
    assert row["bic"] == pytest.approx(row["k"] * math.log(row["n"]) - 2 * row["loglik"])
    assert row["aic"] == pytest.approx(2 * row["k"] - 2 * row["loglik"])
    text = (one / "comparison.md").read_text()
    assert "PXP" in text and "Bayesian omnibus risk" in text and (one / "comparison.png").stat().st_size > 5000
    # the same fit as a two-job multirun, warm cache: the same fits.csv
    two = tmp_path / "two"
    proc = _cli(str(tiny_log), "--out", str(two), *FIT, f"cache={tmp_path / 'scores.sqlite'}", "-m", "shard=0,1",
                "shards=2")
    assert proc.returncode == 0, proc.stderr
    assert "0 score tables computed" in proc.stdout
    a, b = pd.read_csv(one / "fits.csv"), pd.read_csv(two / "fits.csv")
    pd.testing.assert_frame_equal(a, b)
    # another model space into the same directory is refused
    proc = _cli(str(tiny_log), "--out", str(one), *FIT, "depths=[1]", f"cache={tmp_path / 'scores.sqlite'}")
    assert proc.returncode == 2 and "holds fits of another" in proc.stderr, proc.stderr


def test_a_small_cohort_recovers_each_participants_depth_and_beta(tmp_path):
    """Recovery on a cohort whose answer is known.

    8 participants with the veridical predictor (no IPE noise, so the fit sees the
    agents' own scores), beta 20, each its own lapse; 6 tasks of 4 blocks. All
    search to depth 2; under time_limited a budget of one call truncates them to
    myopic. Tolerances, from the measured run (8 of 8 recovered, every |dBIC| >= 5,
    median beta of the winners 21): at least 7 of 8 depths, since a participant
    with few placements and a large lapse can be ambiguous; the median fitted
    beta within a factor of 2 of the true 20, since beta trades off against the lapse
    on about 18 placements each and single fits reach the bound of 200.
    """
    from overhang_framework.config import compose_config
    from overhang_framework.participants import CONFIG_NAME, run

    run(compose_config(["tasks=custom", "tasks.sequences=[[1.2,0.6,1.2,0.6],[0.6,1.2,0.6,0.6],[1.8,0.6,0.6,1.2],"
                        "[1.2,1.2,0.6,1.8],[0.6,0.6,1.8,1.2],[1.8,1.2,0.6,0.6]]", "world.physics=static",
                        "predictor=veridical", "cohort.parameters.sigma=null", "progress=false", "jobs=2",
                        "cohort.participants.time_limited=4", "cohort.participants.unconstrained=4",
                        "cohort.n_tasks=null", "~cohort.parameters.depth", "+cohort.parameters.depth={dist: fixed, value: 2}",
                        "~cohort.parameters.beta", "+cohort.parameters.beta={dist: fixed, value: 20}",
                        "conditions.time_limited.call_limit=1"], config_name=CONFIG_NAME), tmp_path / "sim")
    proc = _cli(str(tmp_path / "sim" / "log.jsonl"), "--out", str(tmp_path / "fit"), "world.physics=static",
                "~models.cnn", "~models.hybrid", "~models.ipe", "+models.veridical={predictor: veridical}",
                "progress=false", f"cache={tmp_path / 'scores.sqlite'}")
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(tmp_path / "fit" / "fits.csv")
    fits = fits[~fits["participant"].str.startswith("pooled:")]
    best = fits.loc[fits.groupby("participant")["bic"].idxmin()]
    effective = best["condition"].map({"time_limited": 1, "unconstrained": 2})
    assert (best["depth"] == effective).sum() >= 7, best[["participant", "model", "bic"]]
    assert 10 <= best["beta"].median() <= 40
