"""Reusable contract test suites, one per interface.

A plugin proves it honours an interface by subclassing the suite in its own
tests and providing the fixture the suite names::

    from overhang_framework.testing.contracts import PredictorContract

    class TestMyPredictor(PredictorContract):
        @pytest.fixture
        def predictor(self, world):
            return MyPredictor(world=world)

The ``world`` fixture defaults to the built-in ``overhang`` world with the
PyBullet reference physics; override it to test against another world.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from overhang_framework.geometry import Action, Geometry
from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, State, Task, Value, World
from overhang_framework.plugins import Registry

EXAMPLE_TASK = Task("contract", (0.6, 1.8, 1.2, 1.8, 0.6, 1.8))


def mid_episode_state(world: World, placements: int = 2) -> State:
    """A state reached by stacking the first ``placements`` blocks of :data:`EXAMPLE_TASK` at x = 0."""
    state = world.initial_state(EXAMPLE_TASK)
    for _ in range(placements):
        layer = max(b.layer for b in state.geometry.blocks) + 1
        state = world.step(state, Action(0.0, layer))
    return state


class _WithWorld:
    @pytest.fixture
    def world(self) -> World:
        return Registry().create("world", {"name": "overhang", "physics": "pybullet"})

    @pytest.fixture
    def state(self, world) -> State:
        return mid_episode_state(world)


class WorldContract(_WithWorld):
    """Provide ``world``."""

    def test_initial_state_has_one_block_on_the_ground(self, world):
        state = world.initial_state(EXAMPLE_TASK)
        assert len(state.geometry) == 1
        assert state.geometry.blocks[0].layer == 0
        assert state.remaining == EXAMPLE_TASK.sequence[1:]

    def test_every_enumerated_action_is_legal_and_steps(self, world, state):
        actions = world.legal_actions(state)
        assert actions, "a mid-episode state has legal actions"
        for a in actions:
            assert world.illegal_reason(state, a) is None
            nxt = world.step(state, a)
            assert len(nxt.geometry) == len(state.geometry) + 1
            assert nxt.remaining == state.remaining[1:]

    def test_illegal_action_is_refused(self, world, state):
        with pytest.raises(ValueError):
            world.step(state, Action(0.0, 0))

    def test_ground_block_alone_is_stable(self, world):
        assert world.is_stable(world.initial_state(EXAMPLE_TASK).geometry)

    def test_reward_is_zero_after_a_collapse(self, world, state):
        assert world.reward(state.geometry, stable_throughout=False) == 0.0
        assert world.reward(state.geometry, stable_throughout=True) == world.overhang(state.geometry) > 0


class PredictorContract(_WithWorld):
    """Provide ``predictor``."""

    def test_one_probability_per_action(self, predictor: Predictor, world, state):
        actions = world.legal_actions(state)
        p = np.asarray(predictor.predict(state, actions, np.random.default_rng(0)))
        assert p.shape == (len(actions),)
        assert np.all((p >= 0) & (p <= 1)) and np.all(np.isfinite(p))

    def test_no_actions_gives_empty_array(self, predictor, state):
        assert np.asarray(predictor.predict(state, [], np.random.default_rng(0))).shape == (0,)

    def test_same_seed_same_prediction(self, predictor, world, state):
        actions = world.legal_actions(state)
        a = predictor.predict(state, actions, np.random.default_rng(7))
        b = predictor.predict(state, actions, np.random.default_rng(7))
        np.testing.assert_array_equal(a, b)

    def test_batched_equals_one_by_one(self, predictor, world, state):
        actions = world.legal_actions(state)[::4]
        batched = predictor.predict(state, actions, np.random.default_rng(3))
        single = [predictor.predict(state, [a], np.random.default_rng(3))[0] for a in actions]
        np.testing.assert_allclose(batched, single)

    def test_many_requests_equal_one_call_each(self, predictor, world, state):
        actions = world.legal_actions(state)
        child = world.successor(state, actions[len(actions) // 2])
        requests = [(state, actions[::3]), (child, world.legal_actions(child)[::3]), (state, [])]
        many = predictor.predict_many(requests, [np.random.default_rng(s) for s in (4, 5, 6)])
        assert len(many) == len(requests)
        for (s, acts), seed, got in zip(requests, (4, 5, 6), many):
            np.testing.assert_allclose(got, predictor.predict(s, acts, np.random.default_rng(seed)), rtol=1e-6)


class PlannerContract(_WithWorld):
    """Provide ``planner``; ``predictor`` and ``value`` default to the built-in veridical and overhang. A planner
    that consults no predictor (a heuristic) says so with a class attribute ``predictor_free = True``, and then
    must spend no predictor call."""

    @pytest.fixture
    def predictor(self, world) -> Predictor:
        return Registry().create("predictor", {"name": "veridical"}, world=world)

    @pytest.fixture
    def value(self, world) -> Value:
        return Registry().create("value", {"name": "overhang"}, world=world)

    def test_plans_a_legal_action_and_reports_spend(self, planner: Planner, predictor, value, world, state):
        decision = planner.plan(state, predictor, value, Budget(), np.random.default_rng(0))
        assert isinstance(decision, Decision)
        assert world.illegal_reason(state, decision.action) is None
        assert 0.0 <= decision.predicted_stability <= 1.0
        assert decision.spend.seconds >= 0
        if getattr(planner, "predictor_free", False):
            assert decision.spend.predictor_calls == 0
        else:
            assert decision.spend.predictor_calls >= 1

    def test_same_seed_same_action(self, planner, predictor, value, state):
        a = planner.plan(state, predictor, value, Budget(), np.random.default_rng(5)).action
        b = planner.plan(state, predictor, value, Budget(), np.random.default_rng(5)).action
        assert a == b

    def test_still_answers_when_the_budget_is_spent(self, planner, predictor, value, world, state):
        decision = planner.plan(state, predictor, value, Budget(seconds=0.0), np.random.default_rng(0))
        assert world.illegal_reason(state, decision.action) is None


class ValueContract(_WithWorld):
    """Provide ``value``."""

    def test_finite_number(self, value: Value, state):
        v = value(state)
        assert isinstance(v, float) and math.isfinite(v)

    def test_empty_geometry_is_allowed(self, value):
        assert math.isfinite(value(State(Geometry(), ())))
