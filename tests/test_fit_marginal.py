"""Fitting with the participant's own noise in the likelihood (overhang_framework.fit.marginal)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))

REPO = Path(__file__).resolve().parents[1]


def assert_likelihood_and_gradient(d, beta, lapse, by_hand):
    """``d``'s log-likelihood is ``by_hand``, and its gradient in (beta, lapse) is the central differences'."""
    value, grad = d.value_and_grad(beta, lapse)
    assert value == pytest.approx(by_hand, rel=1e-12) and d.log_likelihood(beta, lapse) == pytest.approx(by_hand)
    h = 1e-6
    numeric = [(d.log_likelihood(beta + h, lapse) - d.log_likelihood(beta - h, lapse)) / (2 * h),
               (d.log_likelihood(beta, lapse + h) - d.log_likelihood(beta, lapse - h)) / (2 * h)]
    assert grad == pytest.approx(numeric, rel=1e-5)


def test_the_sampled_likelihood_and_its_gradient_are_the_average_softmax_and_its_derivatives():
    from overhang_framework.fit.marginal import SampledDecisions

    rng = np.random.default_rng(0)
    samples = [rng.random((40, n)) for n in (5, 7, 3)]
    chosen = [1, 4, 2]
    d = SampledDecisions.of(samples, chosen)
    beta, lapse = 6.0, 0.1
    by_hand = 0.0
    for s, c in zip(samples, chosen):
        soft = np.exp(beta * s) / np.exp(beta * s).sum(axis=1, keepdims=True)
        by_hand += np.log((1 - lapse) * soft[:, c].mean() + lapse / s.shape[1])
    assert_likelihood_and_gradient(d, beta, lapse, by_hand)
    assert d.subset(np.array([0, 2])).log_likelihood(beta, lapse) == pytest.approx(
        by_hand - np.log((1 - lapse) * (np.exp(beta * samples[1]) / np.exp(beta * samples[1]).sum(
            axis=1, keepdims=True))[:, 4].mean() + lapse / 7))


def test_with_a_motor_model_the_sampled_likelihood_weighs_every_action_and_its_gradient_is_exact():
    from overhang_framework.fit.marginal import SampledDecisions

    rng = np.random.default_rng(1)
    samples = [rng.random((30, n)) for n in (5, 7, 3)]
    weights = [rng.random(n) * (rng.random(n) < 0.6) for n in (5, 7, 3)]
    d = SampledDecisions.of(samples, [0, 0, 0], weights)
    beta, lapse = 4.0, 0.2
    by_hand = 0.0
    for s, w in zip(samples, weights):
        soft = np.exp(beta * s) / np.exp(beta * s).sum(axis=1, keepdims=True)
        by_hand += np.log((1 - lapse) * (soft @ w).mean() + lapse * w.sum() / s.shape[1])
    assert_likelihood_and_gradient(d, beta, lapse, by_hand)
    # one-hot weights are the chosen actions'
    hot = SampledDecisions.of(samples, [1, 4, 2], [np.eye(n)[c] for n, c in zip((5, 7, 3), (1, 4, 2))])
    assert hot.value_and_grad(beta, lapse)[0] == pytest.approx(
        SampledDecisions.of(samples, [1, 4, 2]).value_and_grad(beta, lapse)[0], rel=1e-12)
    assert d.subset(np.array([2])).log_likelihood(beta, lapse) == pytest.approx(
        SampledDecisions.of(samples[2:], [0], weights[2:]).log_likelihood(beta, lapse))


def test_with_a_percept_each_sample_scores_its_seen_towers_actions_and_credits_their_real_placements():
    from overhang_framework.fit.marginal import SampledDecisions

    rng = np.random.default_rng(2)
    samples = [rng.random((20, m)) for m in (6, 4)]
    targets = [rng.integers(0, n, size=(20, m)) for m, n in ((6, 5), (4, 7))]
    targets[1][:, 3] = -1  # a seen tower with fewer actions: padding
    samples[1][:, 3] = -np.inf
    chosen, sizes = [2, 6], [5, 7]
    weights = [rng.random(5), rng.random(7)]
    beta, lapse = 5.0, 0.15
    for w in (None, weights):
        d = SampledDecisions.of(samples, chosen, w, targets, sizes)
        by_hand = 0.0
        for s, t, c, n, i in zip(samples, targets, chosen, sizes, range(2)):
            e = np.where(np.isfinite(s), np.exp(beta * np.where(np.isfinite(s), s, 0)), 0.0)
            soft = e / e.sum(axis=1, keepdims=True)
            credit = (t == c) if w is None else np.where(t >= 0, w[i][np.maximum(t, 0)], 0.0)
            uniform = 1 / n if w is None else w[i].sum() / n
            by_hand += np.log((1 - lapse) * (soft * credit).sum(axis=1).mean() + lapse * uniform)
        assert_likelihood_and_gradient(d, beta, lapse, by_hand)
        assert d.subset(np.array([1])).log_likelihood(beta, lapse) == pytest.approx(
            SampledDecisions.of(samples[1:], chosen[1:], None if w is None else w[1:], targets[1:],
                                sizes[1:]).log_likelihood(beta, lapse))


@pytest.mark.parametrize("params", [dict(depth=1, K=10, switch=3, hand=0.13, percept=0.03, risk=0.9, lapse=0.07),
                                    dict(depth=1, K=10, percept=0.04)])
def test_the_fits_percept_samples_give_the_choice_models_probabilities(params):
    """The fit's likelihood with a percept (towers seen per state, each with its share of the noise draws) is the
    simulated participant's: each action's probability within the Monte Carlo error of ``BankChoice.prob``."""
    from search_fixtures import value as value_fixture, world as world_fixture  # noqa: F401

    from overhang_framework.fit.agreement import build_state
    from overhang_framework.fit.choice import BankChoice, ChoiceParams, VerdictBank
    from overhang_framework.fit.marginal import SampledDecisions, _seed
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    value = registry.create("value", {"name": "overhang"}, world=world)
    bank = VerdictBank(world, sigma=0.03, size=200, seed=99)
    state = build_state(world, "A")
    choice = BankChoice(world, value, bank, ChoiceParams(beta=8.0, **params), draws=1_500, seed=5)
    scores, targets = choice.perceived_samples(state, 1_500, 30, _seed(state, 0))
    n = len(world.legal_actions(state))
    d = SampledDecisions.of([scores] * n, list(range(n)), None, [targets] * n, [n] * n)
    fitted = d.probabilities(8.0, params["lapse"] if "lapse" in params else 0.0)
    assert fitted.sum() == pytest.approx(1.0, abs=1e-9)
    # both are Monte Carlo estimates of 1,500 draws: within four of their joint standard errors (and a percept's
    # share, 30 towers against 1,500, of 0.01)
    assert np.all(np.abs(fitted - choice.prob(state)) < 4 * np.sqrt(2) * choice.prob_error(state) + 0.01)


def test_the_command_fits_k_sigma_and_depth_and_writes_a_comparison(tmp_path):
    """Two myopic and two depth-2 participants (IPE, K = 10): every fitted row names a K and a sigma of the grids,
    the comparison is written, and bad grids are one line."""
    from search_fixtures import simulated_log

    log = simulated_log(tmp_path / "sim", "[[1.2,0.6,1.2],[0.6,1.2,0.6,0.6]]")
    out = tmp_path / "fit"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                           "--sigma", "0.03", "--K", "1,10", "--depths", "1,2", "--draws", "100"],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(out / "fits.csv")
    assert len(fits) == 4 * 2 and set(fits["K"]) <= {1, 10} and set(fits["sigma"]) == {0.03}
    assert (fits["k"] == 3).all()  # beta, lapse and K (one sigma)
    assert "- **Summed BIC:**" in (out / "comparison.md").read_text()
    # whether any model describes them opens the comparison: two a condition on two tasks are too few to tell
    import json

    fitness = json.loads((out / "adequacy.json").read_text())
    assert fitness["verdict"] == "cannot tell" and fitness["placements"] == int(fits.groupby("participant")["n"].first().sum())
    assert (out / "comparison.md").read_text().split("\n")[2] == fitness["sentence"]
    assert "choice_logp" not in fits.columns
    # two worker processes give the same fits; a run stopped with one participant's part missing fits only it
    two = tmp_path / "two"
    args = [sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(two), "--sigma", "0.03",
            "--K", "1,10", "--depths", "1,2", "--draws", "100"]
    proc = subprocess.run(args + ["--jobs", "2"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    pd.testing.assert_frame_equal(pd.read_csv(two / "fits.csv"), fits)
    parts = sorted((two / "parts").glob("*.csv"))
    assert len(parts) == 4
    parts[0].unlink()
    again = subprocess.run(args, capture_output=True, text=True, cwd=REPO)
    assert again.returncode == 0 and "3 participants' fits kept" in again.stderr, again.stderr
    assert "fitted 1 participants" in again.stdout
    pd.testing.assert_frame_equal(pd.read_csv(two / "fits.csv"), fits)
    other = subprocess.run(args[:-1] + ["200"], capture_output=True, text=True, cwd=REPO)
    assert other.returncode == 2 and "holds a fit of other logs or settings" in other.stderr
    motor = subprocess.run(args[:-2] + ["--out", str(tmp_path / "motor"), "--motor-sd", "0.02"], capture_output=True,
                           text=True, cwd=REPO)
    assert motor.returncode == 0, motor.stderr
    assert "is scored where it was made" in (tmp_path / "motor" / "comparison.md").read_text()
    assert '"motor"' in (tmp_path / "motor" / "marginal.json").read_text()
    bad = subprocess.run(args[:-2] + ["--out", str(tmp_path / "bad"), "--motor-sd", "0"], capture_output=True,
                         text=True, cwd=REPO)
    assert bad.returncode == 2 and "--motor-sd must be a number of metres above 0" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                          "--K", "0"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "K, depths, --draws, --bank and --jobs must be whole numbers >= 1" in bad.stderr


def test_the_hand_a_planner_plans_for_is_fitted_on_a_grid(tmp_path):
    from search_fixtures import simulated_log

    log = simulated_log(tmp_path / "sim", "[[1.2,0.6,1.2]]")
    out = tmp_path / "fit"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                           "--sigma", "0.03", "--K", "1", "--depths", "1", "--hand", "0,0.13", "--draws", "50"],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(out / "fits.csv")
    assert set(fits["hand"]) <= {0.0, 0.13} and (fits["k"] == 3).all()  # beta, lapse and the hand
    assert '"hands"' in (out / "marginal.json").read_text()
    bad = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                          "--hand=-0.1"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "sigmas, hands and percepts >= 0" in bad.stderr


def test_the_hybrid_family_and_the_percept_are_fitted_on_their_grids(tmp_path):
    """``--switch 0,3`` fits the IPE and the hybrid as two families, the switch a column of the hybrid's rows; the
    percept a grid axis; the CNN's weights recorded with the settings."""
    from search_fixtures import simulated_log

    log = simulated_log(tmp_path / "sim", "[[1.2,0.6,1.2]]")
    out = tmp_path / "fit"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                           "--sigma", "0.03", "--K", "10", "--depths", "1", "--switch", "0,3", "--percept", "0,0.03",
                           "--percepts", "2", "--draws", "20", "--bank", "20"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(out / "fits.csv")
    assert sorted(set(fits["model"])) == ["hybrid/myopic", "ipe/myopic"]
    assert (fits.loc[fits["family"] == "hybrid", "switch"] == 3).all()
    assert fits.loc[fits["family"] == "ipe", "switch"].isna().all()
    assert set(fits["percept"]) <= {0.0, 0.03} and (fits["k"] == 3).all()  # beta, lapse and the percept
    settings = (out / "marginal.json").read_text()
    assert '"checkpoint_sha256"' in settings and '"percepts": 2' in settings
    # a stated subsample: the first participant by id, fitted into its own directory from the parts kept
    first = tmp_path / "first"
    (first / "parts").mkdir(parents=True)
    for part in (out / "parts").glob("*.csv"):
        (first / "parts" / part.name).write_bytes(part.read_bytes())
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(first),
                           "--sigma", "0.03", "--K", "10", "--depths", "1", "--switch", "0,3", "--percept", "0,0.03",
                           "--percepts", "2", "--draws", "20", "--bank", "20", "--first", "1"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0 and "fitted 0 participants" in proc.stdout, proc.stderr
    sub = pd.read_csv(first / "fits.csv")
    assert set(sub["participant"]) == {sorted(set(fits["participant"]))[0]} and '"first": 1' in (
        first / "marginal.json").read_text()
    bad = subprocess.run([sys.executable, "-m", "overhang_framework.fit.marginal", str(log), "--out", str(out),
                          "--switch=-1"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "switch points must be whole numbers >= 0" in bad.stderr


@pytest.mark.parametrize("module", ["overhang_framework.fit.marginal", "overhang_framework.fit.agreement",
                                    "overhang_framework.fit.compare", "overhang_framework.fit.adequacy"])
def test_each_new_fit_command_explains_itself(module):
    proc = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0 and proc.stdout.startswith("usage: python -m " + module), proc.stderr


def test_against_compares_best_likelihoods_over_the_same_family_and_depths():
    from overhang_framework.fit.marginal import against

    mine = pd.DataFrame({"participant": ["a", "a", "b", "b"], "family": "ipe", "depth": [1, 2, 1, 2],
                         "loglik": [-10.0, -9.0, -20.0, -21.0]})
    theirs = pd.DataFrame({"participant": ["a", "a", "b", "b", "b"], "family": ["ipe", "ipe", "ipe", "ipe", "cnn"],
                           "depth": [1, 3, 1, 2, 1], "loglik": [-9.5, -1.0, -19.0, -25.0, -1.0]})
    out = against(mine, theirs)  # depth 3 and the CNN are not compared
    assert out == {"participants": 2, "higher": 1, "median_gain": pytest.approx(-0.25),
                   "mean_gain": pytest.approx(-0.25)}
