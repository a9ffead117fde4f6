"""Searches that settle unsure verdicts only where they matter give the exhaustive search's answers.

The world here is the static physics with about half of its verdicts hidden behind a "reference"
(``stability_bounds`` says -1 for them, and ``settle`` reveals them): the same situation as the
tiered physics' band, at the cost of static checks, so that many random states can be compared.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from overhang_framework.geometry import Geometry
from overhang_framework.interfaces import Budget, Task
from overhang_framework.optimum import OptimumSearch
from overhang_framework.plugins import Registry
from overhang_framework.search import Expander, root_scores, ties
from overhang_framework.tasks import generate_sequences
from overhang_builtins.world import OverhangWorld


class HidingWorld(OverhangWorld):
    """Static physics whose verdicts, for about half the geometries, only :meth:`settle` reveals."""

    deferred_verdicts = True

    def __init__(self, **kwargs):
        super().__init__(physics="static", **kwargs)
        self.revealed = 0

    @staticmethod
    def hidden(g: Geometry) -> bool:
        return hashlib.blake2b(repr(g.key).encode(), digest_size=2).digest()[0] % 2 == 0

    def stability_bounds(self, geometries):
        verdicts = np.asarray(self.backend.stable_batch(list(geometries)), dtype=np.int8)
        return np.where([self.hidden(g) for g in geometries], -1, verdicts).astype(np.int8)

    def settle(self, geometries):
        geometries = list(geometries)
        self.revealed += len(geometries)
        return super().settle(geometries)


def random_states(n: int, seed: int):
    rng = np.random.default_rng(seed)
    world = HidingWorld()
    states = []
    for k, seq in enumerate(generate_sequences(n, 6, seed=seed)):
        state = world.initial_state(Task(f"t{k}", tuple(seq)))
        for _ in range(int(rng.integers(1, 3))):
            stands = [a for a in world.legal_actions(state) if world.is_stable(world.successor(state, a).geometry)]
            state = world.successor(state, stands[int(rng.integers(len(stands)))])
        states.append(state)
    return states


def models():
    world = HidingWorld()
    registry = Registry()
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    return world, predictor, value


@pytest.mark.parametrize("depth", [1, 2, pytest.param(3, marks=pytest.mark.slow)])
def test_lazy_lookahead_chooses_as_the_exhaustive_search(depth):
    settled = 0
    for state in random_states(6, seed=depth):
        answers = []
        for lazy in (True, False):
            world, predictor, value = models()
            expander = Expander(world, predictor, Budget(), seed=3, lazy=lazy)
            scores = root_scores(expander, value, state, depth, exact_all=False, prefetch=True)
            answers.append((sorted(ties(scores).tolist()), round(float(scores.max()), 9)))
            if lazy:
                settled += world.revealed
        assert answers[0] == answers[1]
    assert settled > 0  # the lazy search did meet hidden verdicts, and settled some


def test_lazy_softmax_scores_are_all_exact():
    for state in random_states(3, seed=11):
        out = []
        for lazy in (True, False):
            world, predictor, value = models()
            out.append(root_scores(Expander(world, predictor, Budget(), seed=3, lazy=lazy), value, state, 2,
                                   exact_all=True))
        np.testing.assert_allclose(out[0], out[1], rtol=0, atol=1e-12)


@pytest.mark.slow
def test_lazy_optimum_equals_the_exhaustive_one_and_settles_fewer():
    for state in random_states(3, seed=5):
        values, revealed = [], []
        for lazy in (True, False):
            world, predictor, _ = models()
            search = OptimumSearch(world, predictor, seed=0)
            search.expander.lazy = lazy
            best, path = search.best_path(state)
            values.append(round(best, 9))
            # lazy: the hidden verdicts it settled; exhaustive: the hidden verdicts it computed
            revealed.append(world.revealed if lazy else sum(
                HidingWorld.hidden(c.geometry) for e in search.expander._memo.values() for c in e.children))
            replay = state
            for action in path:
                assert world.is_stable(world.successor(replay, action).geometry)
                replay = world.successor(replay, action)
            assert world.overhang(replay.geometry) == pytest.approx(best)
        assert values[0] == values[1]
        assert revealed[0] < revealed[1]


def test_code_reading_p_sees_every_verdict():
    world, predictor, _ = models()
    state = random_states(1, seed=2)[0]
    e = Expander(world, predictor, Budget(), seed=3).expand(state)
    assert e.unknown.any()
    full = Expander(models()[0], models()[1], Budget(), seed=3, lazy=False).expand(state).p
    np.testing.assert_array_equal(e.p, full)
    assert not e.unknown.any()
