"""Depth-D lookahead: equal to myopic at D=1, finds counterweights, pruning is exact, budgets truncate."""

import numpy as np
import pytest

from overhang_framework.geometry import Block, Geometry, overhang
from overhang_framework.interfaces import Budget, Predictor, State, Task
from overhang_framework.plugins import Registry
from overhang_framework.search import ChoiceRule, Expander, lookahead_value, root_scores
from overhang_framework.tasks import generate_sequences

REG = Registry()


from search_fixtures import ipe, value, veridical, world  # noqa: E402,F401  (shared fixtures)


def planner(world, name="lookahead", **params):
    return REG.create("planner", {"name": name, **params}, world=world)


def random_states(world, n, seed, min_placed=1, max_placed=3):
    """States reached by random legal placements that the world calls stable."""
    rng = np.random.default_rng(seed)
    states = []
    for seq in generate_sequences(n * 3, 6, seed=seed):
        state = world.initial_state(Task("r", tuple(seq)))
        for _ in range(int(rng.integers(min_placed, max_placed + 1))):
            actions = world.legal_actions(state)
            stable = [a for a in actions if world.is_stable(world.successor(state, a).geometry)]
            state = world.successor(state, stable[rng.integers(len(stable))])
        states.append(state)
        if len(states) == n:
            break
    return states


@pytest.mark.parametrize("predictor_name", ["veridical", "ipe"])
def test_depth_one_chooses_exactly_as_myopic(world, value, request, predictor_name):
    predictor = request.getfixturevalue(predictor_name)
    for i, state in enumerate(random_states(world, 6, seed=1)):
        a = planner(world, "myopic").plan(state, predictor, value, Budget(), np.random.default_rng(i))
        b = planner(world, depth=1).plan(state, predictor, value, Budget(), np.random.default_rng(i))
        assert (a.action, a.predicted_stability, a.choice_probability) == \
               (b.action, b.predicted_stability, b.choice_probability)


def test_depth_two_places_the_counterweight_first_and_myopic_does_not(world, veridical, value):
    # a 1.8 block on a 1.2 base; a 0.6 and then a 1.8 block to place
    state = State(Geometry((Block(1.2, 0.0, 0), Block(1.8, 0.3, 1))), (0.6, 1.8))
    myopic = planner(world, "myopic").plan(state, veridical, value, Budget(), np.random.default_rng(0))
    deep = planner(world, depth=2).plan(state, veridical, value, Budget(), np.random.default_rng(0))

    def best_final(first):
        after = world.successor(state, first)
        return lookahead_value(Expander(world, veridical, Budget(), 0), value, after, 1)

    optimum = max(best_final(a) for a in world.legal_actions(state)
                  if world.is_stable(world.successor(state, a).geometry))
    assert myopic.action.x > 0, "myopic puts the small block out on the overhanging side"
    assert deep.action.x < 0, "lookahead puts it on the far side, as a counterweight"
    assert best_final(deep.action) == pytest.approx(optimum)
    assert best_final(myopic.action) < optimum - 0.3
    assert overhang(world.successor(state, deep.action).geometry) < \
        overhang(world.successor(state, myopic.action).geometry), "the counterweight gives up immediate overhang"


@pytest.mark.parametrize("depth", [2, 3])
def test_pruning_never_changes_the_scores_or_the_choice(world, veridical, ipe, value, depth):
    states = random_states(world, 3 if depth == 2 else 2, seed=depth)
    for predictor in (veridical, ipe):
        for i, state in enumerate(states):
            exact = {}
            for prune in (True, False):
                leaf = value if prune else _NoBound(value)
                e = Expander(world, predictor, Budget(), seed=i)
                exact[prune] = root_scores(e, leaf, state, depth, exact_all=True)
            np.testing.assert_allclose(exact[True], exact[False], rtol=1e-12)
            choices = [planner(world, depth=depth, prune=prune)
                       .plan(state, predictor, value, Budget(), np.random.default_rng(i)) for prune in (True, False)]
            assert choices[0].action == choices[1].action
            assert choices[0].spend.predictor_calls <= choices[1].spend.predictor_calls


def test_pruning_saves_predictor_calls(world, veridical, value):
    pruned = unpruned = 0
    for i, state in enumerate(random_states(world, 2, seed=9, min_placed=1, max_placed=1)):
        for prune in (True, False):
            d = planner(world, depth=3, prune=prune).plan(state, veridical, value, Budget(), np.random.default_rng(i))
            if prune:
                pruned += d.spend.predictor_calls
            else:
                unpruned += d.spend.predictor_calls
    assert pruned < unpruned


class _NoBound:
    def __init__(self, value):
        self.value = value

    def __call__(self, state):
        return self.value(state)

    def bound(self, state, depth):
        return None


def test_a_call_budget_truncates_the_depth_and_is_respected(world, veridical, value):
    state = random_states(world, 1, seed=4, min_placed=1, max_placed=1)[0]
    full = planner(world, depth=3).plan(state, veridical, value, Budget(), np.random.default_rng(0))
    assert full.spend.depth_completed == 3 and full.spend.predictor_calls > 3
    for limit in (1, 3, full.spend.predictor_calls - 1):
        d = planner(world, depth=3).plan(state, veridical, value, Budget(predictor_calls=limit),
                                         np.random.default_rng(0))
        assert d.spend.predictor_calls <= limit
        assert d.spend.depth_completed < 3 and d.spend.budget_exhausted
        assert world.illegal_reason(state, d.action) is None
    one = planner(world, depth=3).plan(state, veridical, value, Budget(predictor_calls=1), np.random.default_rng(0))
    myopic = planner(world, "myopic").plan(state, veridical, value, Budget(), np.random.default_rng(0))
    assert one.spend.depth_completed == 1 and one.action == myopic.action


def test_the_time_limited_condition_records_the_depth_reached(tmp_path):
    import json
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "overhang_framework", "planner=lookahead", "planner.depth=3",
         "condition=time_limited", "condition.time_limit=null", "condition.call_limit=4",
         "world.physics=static", "tasks=example", "progress=false", f"hydra.run.dir={tmp_path}"],
        capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    steps = json.loads((tmp_path / "episodes.jsonl").read_text().splitlines()[0])["steps"]
    depths = [s["spend"]["depth_completed"] for s in steps]
    assert all(s["spend"]["predictor_calls"] <= 4 for s in steps)
    assert min(depths[:3]) < 3 and all(d >= 1 for d in depths)
    assert any(s["spend"]["budget_exhausted"] for s in steps)


def test_softmax_probabilities_sum_to_one_and_become_argmax():
    scores = np.array([1.0, 1.4, 0.2, 1.4 - 1e-3])
    for beta in (0.0, 1.0, 10.0):
        p = ChoiceRule("softmax", beta).probabilities(scores)
        assert p.sum() == pytest.approx(1.0) and np.all(p > 0)
    assert np.allclose(ChoiceRule("softmax", 0.0).probabilities(scores), 0.25)
    hot = ChoiceRule("softmax", 1e6).probabilities(scores)
    np.testing.assert_allclose(hot, ChoiceRule("argmax").probabilities(scores), atol=1e-12)
    rng = np.random.default_rng(0)
    picks = [ChoiceRule("softmax", 1e6).choose(scores, rng).index for _ in range(20)]
    assert set(picks) == {1}


def test_choices_report_rank_and_probability():
    rule = ChoiceRule("softmax", 2.0)
    scores = np.array([0.5, 1.5, 1.0])
    probs = rule.probabilities(scores)
    rng = np.random.default_rng(3)
    seen = {}
    for _ in range(200):
        c = rule.choose(scores, rng)
        seen[c.index] = c
        assert c.probability == pytest.approx(probs[c.index])
    assert {i: c.rank for i, c in seen.items()} == {0: 3, 1: 1, 2: 2}
    tie = ChoiceRule("argmax").choose(np.array([2.0, 1.0, 2.0]), np.random.default_rng(0))
    assert tie.rank == 1 and tie.probability == 0.5


def test_bad_planner_parameters_are_refused(world):
    from overhang_framework.errors import ConfigError

    for params, message in (({"depth": 0}, "depth must be a whole number >= 1"),
                            ({"beam": 0}, "beam must be a whole number >= 1 or null"),
                            ({"choice": "best"}, "unknown choice rule 'best'; allowed: argmax, softmax"),
                            ({"beta": -1}, "beta must be a number >= 0")):
        with pytest.raises(ConfigError, match=message):
            planner(world, **params)


def test_beam_search_is_an_approximation_that_costs_less(world, veridical, value):
    state = random_states(world, 1, seed=5, min_placed=1, max_placed=1)[0]
    full = planner(world, depth=3).plan(state, veridical, value, Budget(), np.random.default_rng(0))
    beam = planner(world, depth=3, beam=2).plan(state, veridical, value, Budget(), np.random.default_rng(0))
    assert beam.spend.predictor_calls < full.spend.predictor_calls
    assert world.illegal_reason(state, beam.action) is None


def test_values_never_exceed_their_bounds(world, veridical):
    overhang_value = REG.create("value", {"name": "overhang"}, world=world)
    rollout = REG.create("value", {"name": "rollout"}, world=world)
    for state in random_states(world, 6, seed=11, min_placed=1, max_placed=3):
        for value in (overhang_value, rollout):
            assert value(state) <= value.bound(state, 0) + 1e-12
            e = Expander(world, veridical, Budget(), seed=0).expand(state)
            for child in e.children[::3]:
                assert value(child) <= value.bound(state, 1) + 1e-12
        # a finished tower is worth its overhang; a rollout never ends below zero
        assert 0.0 <= rollout(state)


def test_the_rollout_value_sees_past_the_horizon(world, veridical):
    rollout = REG.create("value", {"name": "rollout"}, world=world)
    state = State(Geometry((Block(1.2, 0.0, 0), Block(1.8, 0.3, 1))), (0.6, 1.8))
    d = planner(world, depth=1).plan(state, veridical, rollout, Budget(), np.random.default_rng(0))
    greedy = planner(world, "myopic").plan(state, veridical, rollout, Budget(), np.random.default_rng(0))
    assert d.action != greedy.action, "with a rollout leaf value, depth 1 already looks beyond the next block"


class _Network(Predictor):
    """A batched predictor that costs per tower (as a network does), counting the towers it scores."""

    batched = True
    batch_invariant = True
    deterministic = True

    def __init__(self):
        self.towers = 0

    def predict(self, state, actions, rng):
        return self.predict_many([(state, actions)], [rng])[0]

    def predict_many(self, requests, rngs):
        out = []
        for state, actions in requests:
            self.towers += len(actions)
            n = len(state.geometry)
            out.append(np.array([np.clip(1.2 - abs(a.x) / (1 + 0.3 * n), 0, 1) for a in actions]))
        return out


def test_a_networks_deep_unbudgeted_search_expands_nodes_as_it_reaches_them(world, value):
    planner = REG.create("planner", {"name": "lookahead", "depth": 3, "choice": "softmax"}, world=world)
    state = world.initial_state(Task("t", (1.2, 1.8, 0.6, 1.2, 0.6)))
    found = {}
    for prefetch in (True, False):
        network = _Network()
        planner.prefetches = (lambda p, b: True) if prefetch else type(planner).prefetches.__get__(planner)
        d = planner.plan(state, network, value, Budget(), np.random.default_rng(0))
        found[prefetch] = (d.action, d.choice_probability, network.towers)
    assert found[False][:2] == found[True][:2]
    assert found[False][2] < found[True][2]
    default = type(planner).prefetches
    assert not default(planner, _Network(), Budget())
    assert default(planner, _Network(), Budget(predictor_calls=4))  # a budget's charges stay as they were
    assert default(planner, REG.create("predictor", {"name": "veridical"}, world=world), Budget())
    varying = _Network()
    varying.batch_invariant = False  # answers that differ with the batch: prefetched as before, the same numbers
    assert default(planner, varying, Budget())


def test_the_myopic_reward_can_be_the_gain_or_the_final_reward(world, veridical, value):
    state = State(Geometry((Block(1.8, 0.0, 0),)), (1.8, 0.6))
    rng = np.random.default_rng(0)
    plain = planner(world, "myopic").plan(state, veridical, value, Budget(), rng)
    assert overhang(world.successor(state, plain.action).geometry) > 0.9  # extends, standing
    # gain: an action that does not extend scores 0 whatever its risk; one that extends scores p * gain
    gain = planner(world, "myopic", reward="gain")
    after = np.array([1.5, 0.9, 0.6])
    np.testing.assert_allclose(gain.immediate(state, after), [0.6, 0.0, 0.0])
    # final: before the last block every action ties at 0, so the choice is uniform over all of them
    final = planner(world, "myopic", reward="final")
    np.testing.assert_allclose(final.immediate(state, after), 0.0)
    chosen = {final.plan(state, veridical, value, Budget(), np.random.default_rng(i)).action for i in range(40)}
    assert len(chosen) > 10
    last = State(state.geometry, (0.6,))
    np.testing.assert_allclose(final.immediate(last, after), after)
    assert final.plan(last, veridical, value, Budget(), rng).action == \
        planner(world, "myopic").plan(last, veridical, value, Budget(), rng).action
    with pytest.raises(Exception, match="unknown myopic reward 'later'; allowed: overhang, gain, final"):
        planner(world, "myopic", reward="later")


def test_the_reach_bound_from_placement_arrays_equals_the_one_from_actions():
    """max_reach takes a world's placements as arrays when it offers them (legal_xs), else its actions."""
    from overhang_framework.physics.towers import random_towers
    from overhang_framework.interfaces import State
    from overhang_framework.search import max_reach, reach_bound

    world = Registry().create("world", {"name": "overhang", "physics": "static"})

    class ActionsOnly:  # the same world without its arrays
        def __init__(self, inner):
            self.inner = inner

        def legal_actions(self, state, resolution=None):
            return self.inner.legal_actions(state, resolution)

    plain = ActionsOnly(world)
    states = [State(g, widths) for g in random_towers(60, seed=9, min_blocks=1, max_blocks=6)
              for widths in ((0.6,), (1.8, 1.2), ())]
    for s in states:
        for resolution in (None, 0.05):
            assert max_reach(world, s, resolution) == max_reach(plain, s, resolution)
        assert reach_bound(world, s, 2) == reach_bound(plain, s, 2)
    xs, layers = world.legal_xs(states[0])
    assert [(a.x, a.layer) for a in world.legal_actions(states[0])] == list(zip(xs.tolist(), layers.tolist()))
