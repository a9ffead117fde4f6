"""The executed placement's motor noise in the likelihood (fit.motor): the probability of a placement's x given each
planned grid action is what the simulated participant's hand does, and the fit uses it."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.stats import chi2

from overhang_framework.behaviour.participants import _legal_x
from overhang_framework.errors import ConfigError
from overhang_framework.fit.likelihood import Decisions, log_likelihood
from overhang_framework.fit.motor import Motor, weights
from overhang_framework.interfaces import Action, Task

from search_fixtures import world  # noqa: F401

SEQUENCE = (1.2, 0.6, 1.8, 0.6, 1.2, 0.6)


@pytest.fixture(scope="module")
def state(world):
    s = world.initial_state(Task("t", SEQUENCE))
    return world.step(s, Action(0.3, 1))  # a 0.6 block off centre: layer 2's legal x end at its edges


def cells(world, state, j, motor, reach):
    """Every cell of ``motor.precision`` around action ``j`` within ``reach`` metres, and its ``W_j``."""
    a = world.legal_actions(state)[j]
    step = motor.precision
    centres = a.x + step * np.arange(-round(reach / step), round(reach / step) + 1)
    return centres, np.array([weights(world, state, float(c), a.layer, motor)[j] for c in centres])


@pytest.mark.parametrize("sd, which", [(0.05, "first"), (0.05, "last"), (0.05, "middle"), (0.4, "last")])
def test_the_cells_of_a_planned_action_hold_all_its_probability(world, state, sd, which):
    actions = world.legal_actions(state)
    j = {"first": 0, "last": len(actions) - 1, "middle": len(actions) // 2}[which]
    motor = Motor(sd, retries=5, precision=0.002)
    _, w = cells(world, state, j, motor, 7 * sd)
    assert w.sum() == pytest.approx(1.0, abs=2e-3)


@pytest.mark.parametrize("sd, retries", [(0.05, 5), (0.4, 1)])
def test_the_probabilities_are_the_simulated_hands(world, state, sd, retries):
    """20,000 placements of the simulator's hand (drawn again while illegal, else the grid x) around the last legal
    action of layer 2, binned ten cells a bin; a chi-square test of the bins against W. With a hand of 0.4 m and
    one retry many placements fall back to the grid x, and W's point mass there says how many."""
    actions = world.legal_actions(state)
    j = max(i for i, a in enumerate(actions) if a.layer == 2)
    a = actions[j]
    motor = Motor(sd, retries=retries, precision=0.002)
    rng = np.random.default_rng(7)
    draws = np.array([_legal_x(world, state, a, sd, retries, rng) for _ in range(20_000)])
    centres, w = cells(world, state, j, motor, 6 * sd)
    edges = np.append(centres[::10] - 0.001, centres[-1] + 0.001)  # bins on the cells' edges
    observed = np.histogram(draws, edges)[0]
    expected = np.add.reduceat(w, np.arange(0, len(w), 10))[: len(observed)] * len(draws)
    keep = expected > 5
    stat = float((((observed[keep] - expected[keep]) ** 2) / expected[keep]).sum())
    assert chi2.sf(stat, keep.sum() - 1) > 1e-3, (stat, keep.sum())
    fallback = float(np.mean(draws == a.x))
    point = motor_point(world, state, j, motor)
    assert point == pytest.approx(fallback, abs=4 * np.sqrt(max(fallback, 1e-4) / len(draws)))
    if sd == 0.4:
        assert fallback > 0.05


def motor_point(world, state, j, motor):
    """The point mass of action ``j``'s W at its own grid x (the placements that fell back to it)."""
    from overhang_framework.fit.motor import illegal_mass

    a = world.legal_actions(state)[j]
    q = illegal_mass(state.geometry, state.next_width, np.array([a.x]), np.array([a.layer]), motor.sd)[0]
    return q ** (motor.retries + 1)


def test_the_legal_intervals_are_the_rules(world, state):
    from overhang_framework import rules
    from overhang_framework.fit.motor import legal_intervals

    xs = np.linspace(-4, 4, 16001)
    for layer in (1, 2, 3):
        inside = np.zeros(len(xs), dtype=bool)
        for lo, hi in legal_intervals(state.geometry, state.next_width, layer):
            inside |= (xs > lo + 1e-9) & (xs < hi - 1e-9)
        mask = rules.legal_mask(state.geometry, state.next_width, xs, np.full(len(xs), layer))
        assert (inside == mask).mean() > 0.9995, layer


def test_with_one_hot_weights_the_likelihood_is_the_grid_actions():
    rng = np.random.default_rng(0)
    tables = [rng.normal(size=n) for n in (5, 9, 3)]
    chosen = [1, 8, 0]
    plain = Decisions.of(tables, chosen)
    hot = Decisions.of(tables, chosen, [np.eye(len(t))[c] for t, c in zip(tables, chosen)])
    for beta, lapse in ((0.5, 0.0), (7.0, 0.1)):
        assert log_likelihood(hot, beta, lapse) == pytest.approx(log_likelihood(plain, beta, lapse), abs=1e-12)
    assert log_likelihood(hot.subset(np.array([2, 0])), 3.0, 0.05) == pytest.approx(
        log_likelihood(plain.subset(np.array([2, 0])), 3.0, 0.05), abs=1e-12)


@pytest.mark.parametrize("node, message", [
    ({"sd": 0}, "motor.sd must be a number of metres above 0"),
    ({"sd": "0.02"}, "motor.sd must be a number"),
    ({"sd": 0.02, "retries": -1}, "motor.retries must be a whole number from 0 to 100"),
    ({"sd": 0.02, "precison": 0.001}, "motor.precison is not a setting of the motor model; allowed: sd, retries"),
    (0.02, "motor must be null or a mapping"),
])
def test_a_bad_motor_setting_is_one_clear_error(node, message):
    with pytest.raises(ConfigError, match=message):
        Motor.from_config(node)


def test_a_fit_scores_placements_where_they_were_made(tmp_path):
    """Participants with a hand of 6 cm: the fit with the motor model leaves out nothing, says so, records the model,
    and refuses another motor setting into the same directory."""
    from search_fixtures import fixed_cohort

    fixed_cohort(tmp_path / "sim", {"depth": {"dist": "fixed", "value": 1}, "beta": {"dist": "fixed", "value": 20.0},
                                    "lapse": {"dist": "fixed", "value": 0.02}, "sigma": None},
                 3, 4, "predictor=veridical", "cohort.motor.sd=0.06")

    def fit(*extra):
        return subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(tmp_path / "sim" / "log.jsonl"),
                               "--out", str(tmp_path / "fit"), "~models.cnn", "~models.hybrid", "~models.ipe",
                               "+models.veridical={predictor: veridical}", "depths=[1]", "world.physics=static",
                               f"cache={tmp_path / 'scores.sqlite'}", "progress=false", "pooled=false", *extra],
                              capture_output=True, text=True, timeout=600)

    proc = fit("motor={sd: 0.06}")
    assert proc.returncode == 0, proc.stderr
    import json

    import pandas as pd

    assert json.loads((tmp_path / "fit" / "fit.json").read_text())["motor"] == {"sd": 0.06, "retries": 5,
                                                                                  "precision": 0.001}
    fits = pd.read_csv(tmp_path / "fit" / "fits.csv")
    assert (fits["unmapped"] == 0).all() and np.isfinite(fits["loglik"]).all()
    assert "is scored where it was made" in (tmp_path / "fit" / "comparison.md").read_text()
    assert json.loads((tmp_path / "fit" / "adequacy.json").read_text())["placements"] == int(
        fits.groupby("participant")["n"].first().sum())
    proc = fit("motor={sd: 0.03}")
    assert proc.returncode != 0 and "motor" in proc.stderr and "\n" not in proc.stderr.strip()
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(tmp_path / "sim" / "log.jsonl"), "--out",
                           str(tmp_path / "grid"), "states=grid", "motor={sd: 0.06}"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2 and "motor needs states=logged" in proc.stderr
