"""The hand benchmark's reference and rules on a step whose average is known, and its quick run's table."""

import json

import numpy as np
from scipy.special import ndtr

from overhang_framework.bench import hand as bench
from overhang_framework.geometry import Action
from overhang_framework.interfaces import Predictor, Task
from overhang_framework.plugins import Registry


class Step(Predictor):
    """Stands (1) left of ``edge``, falls (0) from it on: the most step-like answer."""

    deterministic = True

    def __init__(self, edge: float):
        self.edge = edge

    def predict(self, state, actions, rng):
        return np.array([1.0 if a.x < self.edge else 0.0 for a in actions])


def test_monte_carlo_and_equal_probability_nodes_find_a_steps_average_that_three_gauss_hermite_nodes_miss():
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    # a 0.6 block over a 1.8 ground block: every shift within 0.9 m of x = 0 is legal, so the average is exact
    state = world.initial_state(Task("step", (1.8, 0.6, 0.6)))
    actions = [Action(round(x, 6), 1) for x in np.arange(-0.1, 0.31, 0.02)]
    inner, sd, edge = Step(0.137), 0.05, 0.137
    exact = ndtr((edge - np.array([a.x for a in actions])) / sd)
    plain, strat = bench.standard_draws(2000, 5)
    ref, ref_se = bench.monte_carlo(bench.sampled_answers(world, inner, state, actions, sd, strat, 0, 1), True)
    mc, _ = bench.monte_carlo(bench.sampled_answers(world, inner, state, actions, sd, plain, 0, 1), False)
    # stratified: one jump inside one stratum of 2000 is off by at most 1/2000
    assert np.max(np.abs(ref - exact)) <= 1 / 2000 + 1e-6
    assert np.all(ref_se <= 1 / 2000 + 1e-12)
    assert np.all(np.abs(mc - exact) <= 4.5 * np.sqrt(exact * (1 - exact) / 2000) + 1e-3)
    # many equal-probability nodes: within 1/(2n) of any single step, and so of the Monte Carlo
    many = bench.rule_hand(world, inner, sd, "equal-probability", 101).predict(state, actions, None)
    assert np.max(np.abs(many - exact)) <= 1 / 202 + 1e-6
    assert np.max(np.abs(many - ref)) <= 1 / 202 + 1 / 2000 + 1e-6
    # the HandPredictor's own 3 Gauss-Hermite nodes are coarse on a step; 3 equal-probability nodes are within 1/6
    three = bench.rule_hand(world, inner, sd, "gauss-hermite", 3).predict(state, actions, None)
    assert np.max(np.abs(three - exact)) > 0.25
    assert np.max(np.abs(bench.rule_hand(world, inner, sd, "equal-probability", 3).predict(state, actions, None)
                         - exact)) <= 1 / 6 + 1e-6


def test_quick_run_prints_the_table_and_writes_its_figures(tmp_path, capsys):
    out = tmp_path / "hand.json"
    assert bench.main(["--quick", "--sd", "0.05", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "inner" in text and "max err" in text and "mean err" in text and "cost" in text
    assert "load average" in text and "wall time" in text
    figures = json.loads(out.read_text())
    assert figures["draws"] == 500 and len(figures["states"]) == 2
    rows = figures["rows"]
    assert {r["inner"] for r in rows} == {"veridical", "ipe K=50"}
    assert {r["rule"] for r in rows} == set(bench.RULES)
    for r in rows:
        assert r["cost"] == r["nodes"] and 0 <= r["mean_error"] <= r["max_error"] <= 1
    assert all(c["plain_vs_reference_over_4se"] <= 2 for c in figures["references"])
