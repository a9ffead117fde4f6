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

from search_fixtures import value, world  # noqa: E402,F401  (shared fixtures: the static world of CONTEXT)


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
    # each table is its own commit: WAL without a flush to disk per commit (NORMAL), so writing is not the cost
    assert cache._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert cache._db.execute("PRAGMA synchronous").fetchone()[0] == 1
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
        ours = bms(L, alpha0=1 / 3)
        assert ours.frequencies == pytest.approx(ref.frequency_mean, abs=1e-6)
        # ours exact, groupBMC's by Dirichlet samples: within 5 of its standard errors at 1,000,000 samples
        assert ours.ep == pytest.approx(ref.exceedance_probability, abs=5 * 0.5 / math.sqrt(1_000_000))
        assert ours.pxp == pytest.approx(ref.protected_exceedance_probability, abs=2e-3)
        ref1 = groupbmc.GroupBMC(L.T, np.ones(3), max_iter=10_000, tolerance=1e-12).get_result()
        assert bms(L).frequencies == pytest.approx(ref1.frequency_mean, abs=1e-6)
    # identical evidence: nothing to choose, the omnibus risk is near 1 and every PXP near 1/K
    flat = bms(np.zeros((30, 4)))
    assert flat.bor > 0.95 and flat.pxp == pytest.approx([0.25] * 4, abs=0.01)


def test_exact_exceedance_probabilities_match_the_closed_form_and_dirichlet_samples():
    from scipy.stats import beta

    from overhang_framework.fit.bms import exceedance

    # two models: P(r_1 > 1/2) under Beta(a_1, a_2)
    for a in ([3.0, 7.0], [1 / 3, 0.5], [40.0, 41.0]):
        assert exceedance(np.array(a))[0] == pytest.approx(beta.sf(0.5, *a), abs=1e-10)
    rng = np.random.default_rng(5)
    for alpha in (np.array([1 / 3, 5.0, 2.5]), rng.uniform(1 / 24, 40, size=24), np.array([80.0, 1.0, 1.0, 1.0])):
        exact = exceedance(alpha)
        assert exact.sum() == pytest.approx(1.0, abs=1e-10) and (exact >= 0).all()
        sampled = exceedance(alpha, samples=400_000, seed=1)
        assert exact == pytest.approx(sampled, abs=5 * 0.5 / math.sqrt(400_000))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "overhang_framework.fit", *args], capture_output=True, text=True)


def test_an_empty_log_or_an_unwritable_out_is_one_line(tmp_path):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n")
    proc = _cli(str(empty), "--out", str(tmp_path / "out"))
    assert proc.returncode == 2 and proc.stderr == f"error: {empty}: no records; give a behaviour log with at least " \
                                                   "one placement\n", proc.stderr
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    proc = _cli(str(empty), "--out", str(blocker / "out"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"error: cannot write the output directory '{blocker / 'out'}'")
    assert "choose another with --out DIR" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "empty.jsonl"]


def test_a_malformed_or_unusable_log_fails_with_one_line(tmp_path):
    from commands import run_each

    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"log_version": 1, "participant": "p"}\n')
    out = ["--out", str(tmp_path / "out")]
    fit = [sys.executable, "-m", "overhang_framework.fit"]
    malformed, missing, no_out, depth, predictor = run_each([
        [*fit, str(bad), *out], [*fit, str(tmp_path / "missing.jsonl"), *out], [*fit, str(bad)],
        [*fit, str(bad), *out, "depths=[1,9]"], [*fit, str(bad), *out, "+models.magic={predictor: crystal_ball}"]])
    assert malformed.returncode == 2 and malformed.stderr.startswith("error: ") \
        and malformed.stderr.count("\n") == 1, malformed.stderr
    assert "bad.jsonl" in malformed.stderr and "line 1" in malformed.stderr
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1 and "missing.jsonl" in missing.stderr, \
        missing.stderr
    assert no_out.returncode == 2 and "--out" in no_out.stderr
    assert depth.returncode == 2 and "fit.depths: 9 is not a depth" in depth.stderr, depth.stderr
    assert predictor.returncode == 2 and "unknown predictor 'crystal_ball'" in predictor.stderr, predictor.stderr
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory):
    """A simulated log: 2 + 2 participants, three short tasks, static physics."""
    from search_fixtures import simulated_log

    return simulated_log(tmp_path_factory.mktemp("sim"), "[[1.2,0.6,1.2],[0.6,1.2,0.6,0.6],[1.8,0.6,0.6]]")


FIT = ["world.physics=static", "~models.cnn", "~models.hybrid", "models.ipe.K=10", "models.ipe.sigma=[0.02,0.06]",
       "+models.veridical={predictor: veridical}", "progress=false"]


@pytest.mark.slow
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
    # the simulated participants' truth, from the participants.csv next to the log, beside the fitted values
    truth = pd.read_csv(tiny_log.parent / "participants.csv")
    assert _truth_rows(text) == _expected_truth_rows(truth, fits, tiny_log)
    assert "- **Simulated participants** (participants.csv): the generating model is" in text
    # the same fit as a two-job multirun, warm cache: the same fits.csv; the log elsewhere, its truth by --truth
    elsewhere = tmp_path / "elsewhere" / "log.jsonl"
    elsewhere.parent.mkdir()
    elsewhere.write_text(tiny_log.read_text())
    two = tmp_path / "two"
    proc = _cli(str(elsewhere), "--out", str(two), *FIT, f"cache={tmp_path / 'scores.sqlite'}", "-m", "shard=0,1",
                "shards=2", "--truth", str(tiny_log.parent / "participants.csv"))
    assert proc.returncode == 0, proc.stderr
    assert "0 score tables computed" in proc.stdout
    a, b = pd.read_csv(one / "fits.csv"), pd.read_csv(two / "fits.csv")
    pd.testing.assert_frame_equal(a, b)
    assert _truth_rows((two / "comparison.md").read_text()) == _truth_rows(text)
    # the same fit with its tables computed on two worker processes, cold cache: the same fits.csv; no truth
    # next to that log, so no truth in the comparison
    three = tmp_path / "three"
    proc = _cli(str(elsewhere), "--out", str(three), *FIT, f"cache={tmp_path / 'other.sqlite'}", "jobs=2")
    assert proc.returncode == 0, proc.stderr
    assert "0 from the cache" in proc.stdout and " 0 score tables computed" not in proc.stdout
    pd.testing.assert_frame_equal(a, pd.read_csv(three / "fits.csv"))
    assert "Simulated participants" not in (three / "comparison.md").read_text()
    # a cold two-job multirun, both jobs at once: they split the states both need (the pooled conditions'),
    # the same fits.csv
    four = tmp_path / "four"
    proc = _cli(str(elsewhere), "--out", str(four), *FIT, f"cache={tmp_path / 'four.sqlite'}", "-m", "shard=0,1",
                "shards=2", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    assert proc.returncode == 0, proc.stderr
    pd.testing.assert_frame_equal(a, pd.read_csv(four / "fits.csv"))
    # another model space into the same directory is refused
    proc = _cli(str(tiny_log), "--out", str(one), *FIT, "depths=[1]", f"cache={tmp_path / 'scores.sqlite'}")
    assert proc.returncode == 2 and "holds fits of another" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_a_fit_killed_part_way_continues_from_its_journal_with_the_same_fits(tmp_path, tiny_log):
    import os
    import signal
    import time

    whole = tmp_path / "whole"
    proc = _cli(str(tiny_log), "--out", str(whole), *FIT, f"cache={tmp_path / 'a.sqlite'}")
    assert proc.returncode == 0, proc.stderr
    assert not list((whole / "parts").glob("*.jsonl"))  # the journal goes once the part is written
    # the same fit on a cold cache of its own, killed (SIGKILL: no clean-up) after its first fits
    out = tmp_path / "stopped"
    args = [sys.executable, "-m", "overhang_framework.fit", str(tiny_log), "--out", str(out), *FIT,
            f"cache={tmp_path / 'b.sqlite'}"]
    job = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    journal = out / "parts" / "shard-0-of-1.fits.jsonl"
    deadline = time.monotonic() + 300
    while job.poll() is None and time.monotonic() < deadline:
        if journal.exists() and journal.read_text().count("\n") >= 3:
            break
        time.sleep(0.02)
    assert job.poll() is None, "the fit ended before it could be stopped"
    os.kill(job.pid, signal.SIGKILL)
    job.wait()
    assert not (out / "fits.csv").exists()
    finished = journal.read_text().count("\n")
    assert 3 <= finished < 24
    with open(journal, "a") as f:
        f.write('{"participant": "sim-')  # a line the kill cut short
    proc = _cli(*args[3:])
    assert proc.returncode == 0, proc.stderr
    assert f"; {finished} fits from the journal of a stopped run)" in proc.stdout, proc.stdout
    pd.testing.assert_frame_equal(pd.read_csv(whole / "fits.csv"), pd.read_csv(out / "fits.csv"))
    assert not journal.exists()


def _section(text: str, title: str) -> list[str]:
    """The lines of the section ``## title`` of a markdown text."""
    lines = text.splitlines()
    start = lines.index(f"## {title}") + 1
    end = next((k for k in range(start, len(lines)) if lines[k].startswith("## ")), len(lines))
    return lines[start:end]


def _table(lines: list[str]) -> list[list[str]]:
    """The cells of the first markdown table among ``lines``, the header row first (the rule row left out)."""
    rows = [line for line in lines if line.startswith("|")]
    return [[c.strip() for c in row.strip().strip("|").split("|")] for k, row in enumerate(rows) if k != 1]


def _truth_rows(text: str) -> dict:
    rows = _table(_section(text, "Simulated participants: true and fitted"))
    header = rows[0]
    return {r[0]: dict(zip(header, r)) for r in rows[1:]}


def _expected_truth_rows(truth: pd.DataFrame, fits: pd.DataFrame, log: Path) -> dict:
    """What the truth table should hold: participants.csv's values and the depth the log's searches reached
    (the median of depth_completed), beside the best fit's model and parameters."""
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.fit.compare import winners

    best = winners(fits).set_index("participant")
    reached = read_log([str(log)]).groupby("participant")["depth_completed"].median()
    out = {}
    for t in truth.itertuples():
        fit = best.loc[t.id]
        out[t.id] = {"participant": t.id, "condition": t.condition,
                     "true model": f"ipe/{'myopic' if t.depth == 1 else f'D{t.depth}'}",
                     "true depth (reached)": f"{t.depth:g} ({reached[t.id]:g})",
                     "true sigma": f"{t.sigma:.3g}", "true switch": "–", "true beta": f"{t.beta:.3g}",
                     "true lapse": f"{t.lapse:.3g}", "best model": fit["model"],
                     "fitted sigma": "–" if pd.isna(fit["sigma"]) else f"{fit['sigma']:.3g}", "fitted switch": "–",
                     "fitted beta": f"{fit['beta']:.3g}", "fitted lapse": f"{fit['lapse']:.3g}"}
    return out


def test_comparison_opens_with_what_was_found_on_fits_whose_answer_is_known(tmp_path):
    """Fits built by hand so that the answer is known: x/myopic is best for every participant of condition
    a and x/D2 for every one of b; y/myopic and y/D2 never are. The summed BIC favours x/myopic by
    6 x 5 = 30; the BMS sees that the models are not equally frequent (y is never best) but cannot single
    one out; the depth differs between the conditions at the smallest p that 6 + 6 participants allow
    (2 / 924), the other parameters are the same in both. With one model far ahead for everyone, the BMS
    separates them."""
    from overhang_framework.fit.compare import comparison

    def rows(bics):
        out = []
        for k in range(12):
            condition = "a" if k < 6 else "b"
            for model, (family, depth) in {"x/myopic": ("x", 1), "x/D2": ("x", 2), "y/myopic": ("y", 1),
                                           "y/D2": ("y", 2)}.items():
                bic = bics[condition][model] + 0.1 * k
                out.append({"participant": f"p{k:02d}", "condition": condition, "model": model, "family": family,
                            "depth": depth, "sigma": np.nan, "beta": 5.0, "lapse": 0.02, "loglik": -bic / 2, "k": 2,
                            "n": 30, "bic": bic, "aic": bic, "unmapped": 0})
        return pd.DataFrame(out)

    split = rows({"a": {"x/myopic": 100.0, "x/D2": 130.0, "y/myopic": 140.0, "y/D2": 150.0},
                  "b": {"x/myopic": 125.0, "x/D2": 100.0, "y/myopic": 140.0, "y/D2": 150.0}})
    text = comparison(split, tmp_path)
    found = [line for line in text.split("\n## ")[0].splitlines() if line.startswith("- ")]
    assert found[0] == ("- **Summed BIC:** x/myopic fits best over the 12 participants (Σ BIC 1356.6; the next, "
                        "x/D2, is 30.0 higher). Each participant's best model: x/D2 for 6, x/myopic for 6.")
    assert found[1].startswith("- **Random-effects BMS** finds that the models are not equally frequent (Bayesian "
                               "omnibus risk 0.0") and "but none stands out" in found[1]
    assert found[2] == ("- **Conditions** (a against b; the depth of each participant's best model, the other "
                        "parameters of one model fitted to every participant): Depth is higher under b than "
                        "under a (2 against 1, p = .002). Beta (p = 1.000) and lapse (p = 1.000) do not differ at "
                        "p < .05.")
    assert len(found) == 4 and found[3].startswith("- **Placements left out:** none")  # no truth: no simulated participants
    # the Conditions table: one cell per header cell, none of them empty
    table = _table(_section(text, "Conditions"))
    assert table[0] == ["parameter", "a", "b", "p"]
    assert all(len(r) == 4 and all(r) for r in table), table
    assert table[1] == ["depth of the best model", "1.000 (n = 6)", "2.000 (n = 6)", ".002"]
    assert [r[0] for r in table[1:]] == ["depth of the best model", "beta of x/myopic", "lapse of x/myopic"]
    # one model far ahead for everyone: the BMS separates the models
    ahead = rows({c: {"x/myopic": 100.0, "x/D2": 160.0, "y/myopic": 170.0, "y/D2": 180.0} for c in "ab"})
    text = comparison(ahead, tmp_path)
    assert "- **Random-effects BMS** separates the models: the most frequent is x/myopic (estimated frequency" in text
    assert "protected exceedance probability 1.00); the Bayesian omnibus risk is < 0.001." in text


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


@pytest.mark.slow
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
    from commands import run_each

    out = tmp_path / "rec"
    cases = ((["generators.ipe.predictor=crystal"], "generators.ipe: unknown predictor 'crystal'"),
             (["+models.m={predictor: crystal}"], "unknown predictor 'crystal'"),
             (["participants=0"], "participants must be a whole number >= 1"),
             (["~models.cnn"], "generators.cnn uses the predictor 'cnn', which no fitted family uses"),
             (["states=nearest"], "states must be one of logged, grid"),
             ([], None))
    argvs = [[sys.executable, "-m", "overhang_framework.fit.recovery"] + (["--out", str(out)] if message else [])
             + args for args, message in cases]
    for (args, message), proc in zip(cases, run_each(argvs)):
        assert proc.returncode == 2 and proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1
        assert (message or "no results directory given") in proc.stderr, proc.stderr
    assert not out.exists()


def test_a_hybrid_shares_the_model_spaces_cnn_and_its_tables_stay_the_same(world, value):
    from overhang_framework.fit.run import Predictors
    from overhang_framework.fit.space import _predictor_config

    cnn_config, hybrid_config = _predictor_config("cnn", {}), _predictor_config("hybrid", {"switch": 3})
    pool = Predictors(Registry(), world)
    hybrid = pool(hybrid_config)
    cnn = pool(cnn_config)
    assert hybrid.late is cnn and pool(cnn_config) is cnn and pool(hybrid_config) is hybrid
    alone = Registry().create("predictor", dict(hybrid_config), world=world)
    assert alone.late is not cnn
    cnn_table = ScoreTables(world, value, cnn, Model(cnn_config, 2), CONTEXT).table(FIRST)
    hits = cnn.counts["cache_hits"]
    shared = ScoreTables(world, value, hybrid, Model(hybrid_config, 2), CONTEXT).table(FIRST)
    assert cnn.counts["cache_hits"] > hits  # the hybrid's late towers came from what the CNN model asked
    assert np.array_equal(shared, ScoreTables(world, value, alone, Model(hybrid_config, 2), CONTEXT).table(FIRST))
    assert not np.array_equal(shared, cnn_table)
    # switch point 2 sends every tower to the CNN (deterministic): its table is the CNN model's, computed once
    from overhang_framework.fit.scores import share_tables

    early_config = _predictor_config("hybrid", {"switch": 2})
    cnn_tables = ScoreTables(world, value, cnn, Model(cnn_config, 2), CONTEXT)
    early = ScoreTables(world, value, pool(early_config), Model(early_config, 2), CONTEXT)
    share_tables([cnn_tables, early])
    assert early.owner(FIRST) is cnn_tables and cnn.deterministic
    got = early.table(FIRST)
    assert early.stats.computed == 0 and cnn_tables.stats.computed == 1
    by_itself = Registry().create("predictor", dict(early_config), world=world)
    np.testing.assert_allclose(got, ScoreTables(world, value, by_itself, Model(early_config, 2), CONTEXT).table(FIRST),
                               rtol=0, atol=1e-6)


def test_engine_settings_leave_a_tables_key_and_draws_alone():
    fast = {"name": "ipe", "K": 50, "sigma": 0.03, "scenes": "arrays", "backend_params": {}}
    reference = {**fast, "scenes": "objects", "backend_params": {"lp_nnls": False}}
    other = {**fast, "K": 40}
    assert Model(fast, 2).key(CONTEXT) == Model(reference, 2).key(CONTEXT) != Model(other, 2).key(CONTEXT)
    assert Model(fast, 2).draw_seed(CONTEXT) == Model(reference, 2).draw_seed(CONTEXT) != Model(other, 2).draw_seed(CONTEXT)
    # the static LP stage set on the world is an engine setting too
    plain = {**CONTEXT, "world": {**CONTEXT["world"], "static": {"margin": 0.001}}}
    world = {**CONTEXT, "world": {**CONTEXT["world"], "static": {"margin": 0.001, "lp_nnls": False}}}
    assert Model(fast, 2).key(world) == Model(fast, 2).key(plain)
    assert Model(fast, 2).draw_seed(world) == Model(fast, 2).draw_seed(plain)


def test_one_process_computes_every_models_tables_of_a_state_together_in_the_states_order(monkeypatch):
    from types import SimpleNamespace

    from overhang_framework import parallel
    from overhang_framework.fit import run

    states = [state([[1.2, 0.0, 0], [0.6, 0.1 * i, 1]], [1.2]) for i in range(6)]
    known = [{2}, set(), {0, 1, 2, 3, 4, 5}]  # model 2 has every table already
    computed = []

    class Tables(SimpleNamespace):
        def known(self, s, keep=True):
            return states.index(s) in known[self.k]

        def owner(self, s):
            return self

        def compute(self, s):
            computed.append((self.k, states.index(s)))

    monkeypatch.setattr(parallel, "pool_map", lambda *a: pytest.fail("one job needs no worker process"))
    tables = [Tables(k=k, context=CONTEXT, model=Model({"name": "ipe"}, 1), cache=None) for k in (0, 1, 2)]
    totals, ticks = [], []
    run.fill_tables(tables, states + states[:3], jobs=1, on_table=lambda: ticks.append(1), on_total=totals.append)
    # state by state, and within a state every model that lacks its table: a hybrid's parts then answer
    # from what the models of their settings asked just before
    assert computed == [(k, i) for i in range(6) for k in (0, 1) if (k, i) != (0, 2)]
    assert totals == [11] and len(ticks) == 11


def test_worker_processes_compute_a_risk_averse_models_tables_with_its_risk(world, value, tmp_path):
    """Tables filled by two worker processes are the ones this process computes, for a risk-averse model too
    (a worker rebuilds each model whole: its risk, not only its predictor), and are kept in the cache under that
    model's key."""
    from overhang_framework.fit import run

    ipe = {"name": "ipe", "K": 10, "sigma": 0.05}
    states = [FIRST, SECOND] + [state([[1.2, 0.0, 0], [0.6, 0.1 * i, 1]], [1.2, 0.6]) for i in range(6)]

    def make(risk, cache=None):
        return ScoreTables(world, value, Registry().create("predictor", dict(ipe), world=world),
                           Model(ipe, 2, "risk", risk=risk), CONTEXT, cache)

    here = [make(0.0), make(0.8)]
    for t in here:
        for s in states:
            t.compute(s)
    cache = ScoreCache(tmp_path / "scores.sqlite")
    there = [make(0.0, cache), make(0.8, cache)]
    run.fill_tables(there, states, jobs=2)
    for a, b in zip(here, there):
        for s in states:
            assert np.array_equal(a.table(s), b.table(s))
            assert np.array_equal(cache.get(ScoreCache.entry(b.key, s)), a.table(s))
    assert any(not np.allclose(here[0].table(s), here[1].table(s)) for s in states)


def test_jobs_sharing_a_cache_split_the_states_they_all_need_and_balance_their_tables():
    from overhang_framework.fit import run
    from overhang_framework.search import state_key

    states = [state([[1.2, 0.0, 0], [0.6, 0.1 * i, 1]], [1.2]) for i in range(30)]
    # three jobs: 0 needs states 0-19, 1 needs 10-29, 2 needs 5-14 and 25-29; a state costs 1-3 tables
    needs = [range(0, 20), range(10, 30), [*range(5, 15), *range(25, 30)]]
    cost = {i: 1 + i % 3 for i in range(30)}
    rows = [[(states[i], list(range(cost[i]))) for i in need] for need in needs]
    split = run.split_states(rows)
    assert set(split) == {state_key(s) for s in states}
    for i, s in enumerate(states):  # every state goes to a job that needs it
        assert i in needs[split[state_key(s)]]
    load = [sum(cost[i] for i in range(30) if split[state_key(states[i])] == k) for k in range(3)]
    assert sum(load) == sum(cost.values()) and max(load) - min(load) <= max(cost.values())
    # each job reaches the same split whatever order its own states are listed in
    assert run.split_states([r[::-1] for r in rows]) == split


def test_a_job_computes_its_share_first_then_reads_what_the_others_wrote_meeting_them_from_the_far_end(
        world, value, tmp_path, monkeypatch):
    from overhang_framework import parallel
    from overhang_framework.fit import run
    from overhang_framework.search import state_key

    states = [state([[1.2, 0.0, 0], [0.6, 0.05 * i - 0.3, 1]], [1.2]) for i in range(12)]
    mine, theirs = states[:9], states[3:][::-1]  # states 3-8 are needed by both jobs, listed in other orders
    cache = ScoreCache(tmp_path / "scores.sqlite")
    ours = tables(world, value, {"name": "veridical"}, 1, cache)
    other = tables(world, value, {"name": "veridical"}, 1, ScoreCache(tmp_path / "scores.sqlite"))
    split = run.split_states([[(s, [0]) for s in mine], [(s, [0]) for s in theirs]])
    given = [s for s in mine if split[state_key(s)] == 0]
    others = [s for s in theirs if split[state_key(s)] == 1 and s in mine]  # the other's share, in its order
    assert given and len(others) >= 2
    computed = []
    compute = ScoreTables.compute

    def counted(self, s):
        if self is ours:
            computed.append(states.index(s))
            if s is given[-1]:  # meanwhile the other job has done the first of its share
                other.compute(others[0])
        compute(self, s)

    monkeypatch.setattr(ScoreTables, "compute", counted)
    monkeypatch.setattr(parallel, "pool_map", lambda *a: pytest.fail("one job needs no worker process"))
    totals = []
    run.fill_tables([ours], mine, jobs=1, on_total=totals.append, shards=[mine, theirs], shard=0)
    # its share, then the other's from its far end; the table the other wrote is read, not computed
    assert computed == [states.index(s) for s in given + others[::-1]]  # compute() reads the cache first
    assert ours.stats.computed == len(given) + len(others) - 1 and ours.stats.cached == 1
    assert totals == [9]  # an upper bound: the other job wrote one of them first
    # looking at another job's states keeps nothing in memory and counts nothing
    fresh = tables(world, value, {"name": "veridical"}, 1, cache)
    assert all(fresh.known(s, keep=False) for s in mine) and not fresh.known(states[11], keep=False)
    assert not fresh._tables and fresh.stats.cached == 0
    assert state_key(states[0]) not in {state_key(s) for s in theirs} and fresh.known(states[0]) and fresh._tables
    assert ScoreCache.entry(fresh.key, states[0]) in cache and "x" not in cache and "x" not in ScoreCache(None)


def test_worker_items_keep_the_states_order_and_ask_each_missing_table_once(monkeypatch):
    from types import SimpleNamespace

    from overhang_framework import parallel
    from overhang_framework.fit import run

    states = [state([[1.2, 0.0, 0], [0.6, 0.1 * i, 1]], [1.2]) for i in range(10)]
    known = [{3, 4}, set()]  # model 0 already has the tables of states 3 and 4

    class Tables(SimpleNamespace):
        def known(self, s, keep=True):
            return states.index(s) in known[self.k]

        def owner(self, s):
            return self

    tables = [Tables(k=k, context=CONTEXT, model=Model({"name": "ipe"}, 1), cache=None) for k in (0, 1)]
    seen = {}

    def pool_map(setup, args, work, items, jobs, tick):
        seen.update(items=items, args=args)
        return []

    monkeypatch.setattr(parallel, "pool_map", pool_map)
    totals = []
    run.fill_tables(tables, states + states[:2], jobs=2, on_total=totals.append)
    asked = [(k, states.index(s)) for item in seen["items"] for k, chunk in item for s in chunk]
    assert totals == [18] and len(asked) == 18 and len(set(asked)) == 18
    assert [i for k, i in asked if k == 1] == list(range(10)) and [i for k, i in asked if k == 0] == [0, 1, 2, 5, 6, 7, 8, 9]
    assert len(seen["items"]) >= 2 * 2  # enough items for two workers
    assert seen["args"][-1] is None  # no cache for the workers to read
    # jobs sharing a cache: the workers are given its path, and this job's share comes first, then the
    # other job's share from its far end
    for t in tables:
        t.cache = SimpleNamespace(path="scores.sqlite")
    theirs = states[5:] + states[10:]
    run.fill_tables(tables, states, jobs=2, shards=[states, theirs], shard=0)
    from overhang_framework.search import state_key

    split = run.split_states([run._missing(tables, states), run._missing(tables, theirs)])
    given = [i for i, s in enumerate(states) if split[state_key(s)] == 0]
    others = [i for i, s in enumerate(states) if split[state_key(s)] == 1]
    order = list(dict.fromkeys(states.index(s) for item in seen["items"] for k, chunk in item for s in chunk))
    assert others and order == given + others[::-1] and seen["args"][-1] == "scores.sqlite"


def test_the_fit_takes_its_model_space_from_conf_space_and_the_explanations_space_is_the_recoverys(capsys):
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.fit.__main__ import main
    from overhang_framework.fit.space import model_space

    default = compose_config([], config_name="fit")
    assert sorted(default.models) == ["cnn", "hybrid", "ipe"] and list(default.depths) == [1, 2]
    explained = compose_config(["space=explanations"], config_name="fit")
    recovery = compose_config([], config_name="recovery_explanations")
    assert OmegaConf.to_container(explained.models) == OmegaConf.to_container(recovery.models)
    space = model_space(OmegaConf.to_container(explained.models), list(explained.depths))
    assert {i.label for i in space} == {f"{f}/{d}" for f in ("plain", "noise", "risk", "hand", "percept")
                                        for d in ("myopic", "D2")}
    assert {m.risk for i in space if i.label == "risk/D2" for m in i.variants} == {0.5, 0.7, 0.9}
    # overrides change a chosen space as they change the default
    less = compose_config(["space=explanations", "~models.percept", "depths=[1]"], config_name="fit")
    assert "percept" not in less.models and list(less.depths) == [1]
    with pytest.raises(SystemExit) as stop:
        main(["log.jsonl", "--out", "out", "space=nope"])
    assert stop.value.code == 2 and "unknown space 'nope'; available: default, explanations" in capsys.readouterr().err


def test_recovery_counts_a_parameter_only_where_its_generator_draws_it():
    from overhang_framework.fit.recovery import summarise

    rng = np.random.default_rng(3)
    fixed = pd.DataFrame({"generator": "none", "true_sigma": 0.02, "fitted_sigma": 0.02,
                          "true_beta": rng.uniform(2, 20, 30), "true_lapse": rng.uniform(0, 0.1, 30)})
    drawn_sigma = rng.uniform(0.05, 0.12, 30)
    noisy = pd.DataFrame({"generator": "noise", "true_sigma": drawn_sigma,
                          "fitted_sigma": rng.permutation(drawn_sigma),  # fitted unrelated to the truth
                          "true_beta": rng.uniform(2, 20, 30), "true_lapse": rng.uniform(0, 0.1, 30)})
    table = pd.concat([fixed, noisy], ignore_index=True)
    table["fitted_beta"], table["fitted_lapse"] = table["true_beta"], table["true_lapse"]
    table["true_model"] = table["winner"] = "m"
    table["true_family"] = table["winner_family"] = "f"
    table["true_depth"] = table["fitted_depth"] = 2
    summary = summarise(table, ["m"])
    # the 30 fixed and trivially "recovered" sigmas would lift r far above what the noisy generator shows
    assert summary["sigma"]["n"] == 30 and summary["sigma"]["generators"] == ["noise"]
    assert summary["sigma"]["r"] == pytest.approx(np.corrcoef(noisy["true_sigma"], noisy["fitted_sigma"])[0, 1])
    assert summary["sigma"]["r"] < 0.5 and not summary["targets"]["sigma_r"]["met"]
    assert summary["beta"]["n"] == 60 and summary["beta"]["generators"] == ["noise", "none"]


def test_recovery_counts_a_lone_participant_and_a_nameless_generators_fixed_parameter_as_such():
    from overhang_framework.fit.recovery import drawn

    table = pd.DataFrame({"generator": [None, None, "lone", "noise", "noise"],
                          "true_sigma": [0.02, 0.02, 0.07, 0.05, 0.09]})
    # a generator whose name reads back empty still holds sigma fixed; one participant cannot show it
    assert drawn(table, "true_sigma").tolist() == [False, False, True, True, True]
    assert not drawn(table, "true_hand").any()
