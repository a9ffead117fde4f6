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
    # the same fit with its tables computed on two worker processes, cold cache: the same fits.csv
    three = tmp_path / "three"
    proc = _cli(str(tiny_log), "--out", str(three), *FIT, f"cache={tmp_path / 'other.sqlite'}", "jobs=2")
    assert proc.returncode == 0, proc.stderr
    assert "0 from the cache" in proc.stdout and " 0 score tables computed" not in proc.stdout
    pd.testing.assert_frame_equal(a, pd.read_csv(three / "fits.csv"))
    # another model space into the same directory is refused
    proc = _cli(str(tiny_log), "--out", str(one), *FIT, "depths=[1]", f"cache={tmp_path / 'scores.sqlite'}")
    assert proc.returncode == 2 and "holds fits of another" in proc.stderr, proc.stderr


def test_grid_states_replay_each_trial_so_that_the_same_grid_choices_share_states(world):
    """Two participants whose x differ by motor noise but map to the same grid actions meet the same grid
    states; the logged towers differ. An unmapped placement sends its trial back to the logged tower."""
    from overhang_framework.fit.fitting import Placement, map_placements
    from overhang_framework.search import state_key

    def trial(pid, xs):
        placements, tower = [], [[1.2, 0.0, 0]]
        remaining = [0.6, 1.2, 0.6]
        for step, (x, layer) in enumerate(xs, start=1):
            placements.append(Placement(pid, "c", state(tower, remaining), x, layer, trial=1, step=step))
            tower = tower + [[remaining[0], x, layer]]
            remaining = remaining[1:]
        return placements

    a = trial("a", [(0.42, 1), (0.13, 2), (0.0, 3)])
    b = trial("b", [(0.38, 1), (0.08, 2), (0.03, 3)])
    grid = map_placements(world, a + b, "grid")
    logged = map_placements(world, a + b, "logged")
    assert grid.unmapped == 0 and grid.chosen[:3] == grid.chosen[3:]
    assert [state_key(s) for s in grid.states[:3]] == [state_key(s) for s in grid.states[3:]]
    assert len({state_key(s) for s in logged.states}) == 5       # only the first state is shared
    second = grid.states[1]
    assert [blk.x for blk in second.geometry.blocks] == pytest.approx([0.0, 0.4])
    assert logged.chosen == grid.chosen                          # the same actions, from nearby towers
    # an unmapped placement (nothing legal within a grid step) is left out; the next state is the logged one
    c = trial("c", [(0.42, 1), (0.13, 5), (0.0, 2)])
    mapped = map_placements(world, c, "grid")
    assert mapped.unmapped == 1 and len(mapped.states) == 2
    assert mapped.states[1].geometry == c[2].state.geometry
    with pytest.raises(ValueError, match="allowed: logged, grid"):
        map_placements(world, c, "nearest")


def test_recovery_of_a_small_cohort_whose_answer_is_known(tmp_path):
    """The recovery command on a cohort whose answer is known.

    8 unconstrained participants with the veridical predictor (no noise, so the fit
    sees the agents' own scores), depth 1 or 2 (drawn), beta 20 and lapses of their
    own; 6 paper tasks each. Tolerances, from the measured run (8 of 8 depths,
    median fitted beta 20.7, fitted lapses 0 to 0.17 against 0.004 to 0.04): at least 7 of 8 depths, since a participant with a
    large lapse can be ambiguous on 30 placements; the median fitted beta within a
    factor of 2 of the true 20, since beta trades off against the lapse and single
    fits can reach the bound of 200.
    """
    out = tmp_path / "rec"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.recovery", "--out", str(out),
                           "world.physics=static", "~generators.ipe", "~generators.cnn", "~generators.hybrid",
                           "+generators.veridical={predictor: veridical}", "~models.ipe", "~models.cnn",
                           "~models.hybrid", "+models.veridical={predictor: veridical}", "participants=8",
                           "n_tasks=6", "~parameters.beta", "+parameters.beta={dist: fixed, value: 20}", "progress=false", "jobs=2",
                           f"cache={tmp_path / 'scores.sqlite'}"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "recovery.json").read_text())
    table = pd.read_csv(out / "recovery.csv")
    assert summary["participants"] == 8 == len(table)
    assert set(table["true_depth"]) <= {1, 2} and table["generator"].eq("veridical").all()
    assert table["true_family"].eq("veridical").all()
    assert (table["fitted_depth"] == table["true_depth"]).sum() >= 7, table
    assert summary["depth_recovered"] == pytest.approx((table["fitted_depth"] == table["true_depth"]).mean())
    assert 10 <= table["fitted_beta"].median() <= 40
    text = (out / "recovery.md").read_text()
    assert "| veridical/myopic |" in text and "## Model: generating against winning" in text
    assert (out / "recovery.png").stat().st_size > 5000
    assert "participants: depth" in proc.stdout


def test_recovery_refuses_bad_settings_in_one_line_before_it_writes_anything(tmp_path):
    out = tmp_path / "rec"
    for args, message in ((["generators.ipe.predictor=crystal"], "generators.ipe: unknown predictor 'crystal'"),
                          (["+models.m={predictor: crystal}"], "unknown predictor 'crystal'"),
                          (["participants=0"], "participants must be a whole number >= 1"),
                          (["~models.cnn"], "generators.cnn uses the predictor 'cnn', which no fitted family uses"),
                          (["states=nearest"], "states must be one of logged, grid"),
                          ([], None)):
        argv = [sys.executable, "-m", "overhang_framework.fit.recovery"] + (["--out", str(out)] if message else [])
        proc = subprocess.run(argv + args, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2 and proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1
        assert (message or "no results directory given") in proc.stderr, proc.stderr
    assert not out.exists()
