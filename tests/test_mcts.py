"""MCTS: honours the planner contract and its budgets, is seeded, and finds what exhaustive lookahead finds."""

import json
import subprocess
import sys

import numpy as np
import pytest

from overhang_framework.geometry import Block, Geometry
from overhang_framework.interfaces import Budget, State
from overhang_framework.plugins import Registry
from overhang_framework.search import Expander, lookahead_value, root_scores
from overhang_framework.testing.contracts import PlannerContract, mid_episode_state

REG = Registry()


from search_fixtures import ipe, value, veridical, world  # noqa: E402,F401  (shared fixtures)


@pytest.fixture(scope="module")
def state(world):
    return mid_episode_state(world, placements=1)


def planner(world, name="mcts", **params):
    return REG.create("planner", {"name": name, **params}, world=world)


class TestMCTSContract(PlannerContract):
    @pytest.fixture
    def world(self):
        return REG.create("world", {"name": "overhang", "physics": "static"})

    @pytest.fixture
    def planner(self, world):
        return planner(world, iterations=30)


def _counterweight_state():
    # a 1.8 block on a 1.2 base; a 0.6 and then a 1.8 block to place (as in test_lookahead.py)
    return State(Geometry((Block(1.2, 0.0, 0), Block(1.8, 0.3, 1))), (0.6, 1.8))


@pytest.mark.parametrize("rollout", [None, "greedy", "random"])
def test_finds_the_counterweight_that_exhaustive_lookahead_finds(world, veridical, value, rollout):
    state = _counterweight_state()
    deep = planner(world, "lookahead", depth=2).plan(state, veridical, value, Budget(), np.random.default_rng(0))
    found = planner(world, iterations=300, rollout=rollout).plan(state, veridical, value, Budget(),
                                                                np.random.default_rng(0))

    def best_final(first):
        after = world.successor(state, first)
        assert world.is_stable(after.geometry)
        return lookahead_value(Expander(world, veridical, Budget(), 0), value, after, 1)

    assert found.action.x < 0, "MCTS puts the small block on the far side, as a counterweight"
    assert best_final(found.action) == pytest.approx(best_final(deep.action))
    assert 0 < found.spend.iterations <= 300 and found.spend.depth_completed == 2


def test_full_depth_choice_matches_exhaustive_lookahead_on_a_mid_episode_state(world, ipe, value):
    state = mid_episode_state(world, placements=3)  # two placements left: depth 2 is the whole episode
    assert len(state.remaining) == 2
    # the decision's seed, drawn first from the episode's generator, fixes the predictor's draws for both
    seed = int(np.random.default_rng(2).integers(2**63))
    exact = root_scores(Expander(world, ipe, Budget(), seed), value, state, 2, exact_all=True)
    found = planner(world, iterations=400).plan(state, ipe, value, Budget(), np.random.default_rng(2))
    index = world.legal_actions(state).index(found.action)
    assert exact[index] == pytest.approx(exact.max())


def test_an_exhausted_tree_stops_the_search_and_plays_the_exact_best(world, veridical, value):
    state = _counterweight_state()
    exact = root_scores(Expander(world, veridical, Budget(), 0), value, state, 2, exact_all=True)
    for backup, stops in (("max", True), ("mean", False)):
        d = planner(world, iterations=1000, backup=backup).plan(state, veridical, value, Budget(),
                                                               np.random.default_rng(0))
        assert (d.spend.iterations < 1000) == stops
        assert exact[world.legal_actions(state).index(d.action)] == pytest.approx(exact.max())


def test_iterations_bound_the_search(world, veridical, value, state):
    for n in (0, 1, 7):
        d = planner(world, iterations=n).plan(state, veridical, value, Budget(), np.random.default_rng(0))
        assert d.spend.iterations == n
        assert 1 <= d.spend.predictor_calls <= n + 1 and d.spend.nodes_expanded == d.spend.predictor_calls
        assert not d.spend.budget_exhausted
    none = planner(world, iterations=0).plan(state, veridical, value, Budget(), np.random.default_rng(0))
    myopic = planner(world, "myopic").plan(state, veridical, value, Budget(), np.random.default_rng(0))
    assert none.action == myopic.action and none.spend.depth_completed == 1


def test_a_predictor_call_budget_is_respected(world, veridical, ipe, value, state):
    for predictor in (veridical, ipe):
        for limit in (1, 2, 5):
            d = planner(world, iterations=1000).plan(state, predictor, value, Budget(predictor_calls=limit),
                                                     np.random.default_rng(0))
            assert d.spend.predictor_calls <= limit and d.spend.budget_exhausted
            assert d.spend.iterations < 1000
            assert world.illegal_reason(state, d.action) is None


def test_a_spent_time_budget_still_answers_legally(world, veridical, value, state):
    d = planner(world, iterations=1000).plan(state, veridical, value, Budget(seconds=0.0), np.random.default_rng(0))
    assert world.illegal_reason(state, d.action) is None
    assert d.spend.iterations == 0 and d.spend.predictor_calls == 1 and d.spend.budget_exhausted


def test_same_seed_same_decision_and_seeds_differ_only_by_ties(world, ipe, value, state):
    def run(seed, **params):
        return planner(world, iterations=15, **params).plan(state, ipe, value, Budget(), np.random.default_rng(seed))

    a, b = run(3), run(3)
    assert (a.action, a.choice_probability, a.choice_rank, a.spend.predictor_calls) == \
           (b.action, b.choice_probability, b.choice_rank, b.spend.predictor_calls)
    for seed in range(2):
        d = run(seed)
        assert d.choice_rank == 1 and 0 < d.choice_probability <= 1
    s, t = run(5, choice="softmax", beta=2.0), run(5, choice="softmax", beta=2.0)
    assert (s.action, s.choice_probability) == (t.action, t.choice_probability)
    assert 0 < s.choice_probability < 1 and s.choice_rank >= 1


def test_softmax_becomes_argmax_of_the_root_values(world, veridical, value):
    state = _counterweight_state()
    hot = planner(world, iterations=300, choice="softmax", beta=1e6).plan(
        state, veridical, value, Budget(), np.random.default_rng(0))
    assert hot.action.x < 0 and hot.choice_rank == 1


def test_bad_planner_parameters_are_refused(world):
    from overhang_framework.errors import ConfigError

    for params, message in (({"iterations": -1}, "iterations must be a whole number >= 0"),
                            ({"iterations": 1.5}, "iterations must be a whole number >= 0"),
                            ({"c": -0.1}, "c must be a number >= 0"),
                            ({"widening": 0.5}, "widening must be a number >= 1"),
                            ({"alpha": 2}, r"alpha must be a number in \[0, 1\]"),
                            ({"rollout": "smart"}, "unknown rollout 'smart'; allowed: null, greedy, random"),
                            ({"backup": "min"}, "unknown backup 'min'; allowed: mean, max"),
                            ({"choice": "best"}, "unknown choice rule 'best'; allowed: argmax, softmax"),
                            ({"beta": -1}, "beta must be a number >= 0")):
        with pytest.raises(ConfigError, match=message) as info:
            planner(world, **params)
        assert "\n" not in str(info.value)


def test_runs_end_to_end_and_records_iterations(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "overhang_framework", "planner=mcts", "planner.iterations=20",
         "world.physics=static", "tasks=example", "progress=false", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    episode = json.loads((tmp_path / "episodes.jsonl").read_text().splitlines()[0])
    assert episode["steps"]
    steps = episode["steps"]
    assert len(steps) == 5, "the example task places five blocks"
    # the last placement's children are all final towers: the tree is exhausted before any simulation
    assert [s["spend"]["iterations"] >= 1 for s in steps] == [True] * 4 + [False]
    for step in steps:
        assert step["spend"]["depth_completed"] >= 1
        assert 1 <= step["spend"]["predictor_calls"] <= 21


def _references(world) -> int:
    return world.backend.backend.counts["reference"]  # the tiered physics under the world's cache


# about 15 s of one core each; tests/test_bench.py runs the argmax case's benchmark in the default suite
@pytest.mark.slow
@pytest.mark.parametrize("choice", ["argmax", "softmax"])
def test_settling_only_the_needed_answers_changes_no_choice_and_runs_fewer_references(choice):
    """With the world's verdicts (tiered physics: a full-window reference run for the towers its static stages
    cannot judge), the lazy search makes the eager search's decisions, from fewer reference runs."""
    decisions, references = {}, {}
    for lazy in (False, True):
        world = REG.create("world", {"name": "overhang", "physics": "tiered"})
        veridical = REG.create("predictor", {"name": "veridical"}, world=world)
        value = REG.create("value", {"name": "overhang"}, world=world)
        mcts = planner(world, iterations=25, lazy=lazy, choice=choice, beta=5.0)
        got = []
        for state in (_counterweight_state(), mid_episode_state(world, placements=2)):
            d = mcts.plan(state, veridical, value, Budget(), np.random.default_rng(3))
            got.append((d.action, d.predicted_stability, d.choice_probability, d.choice_rank, d.spend.iterations,
                        d.spend.predictor_calls,
                        d.spend.depth_completed))
        decisions[lazy], references[lazy] = got, _references(world)
    assert decisions[True] == decisions[False]
    assert 0 < references[True] < references[False]


def test_lazy_must_be_a_boolean(world):
    with pytest.raises(ValueError, match="lazy must be true or false, got 'yes'"):
        planner(world, lazy="yes")
