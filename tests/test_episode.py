"""Episodes: the world's physics decides, the episode ends at the first collapse, reward follows the rules."""

import numpy as np
import pytest

from overhang_framework.episode import episode_rng, run_episode
from overhang_framework.geometry import Geometry
from overhang_framework.interfaces import Decision, Planner, Spend, Task
from overhang_framework.plugins import Registry


@pytest.fixture(scope="module")
def models():
    reg = Registry()
    world = reg.create("world", {"name": "overhang", "physics": "pybullet"})
    return {
        "world": world,
        "predictor": reg.create("predictor", {"name": "veridical"}, world=world),
        "value": reg.create("value", {"name": "overhang"}, world=world),
        "planner": reg.create("planner", {"name": "myopic"}, world=world),
    }


class Reckless(Planner):
    """Takes the legal action of largest immediate overhang, whatever the physics says."""

    def __init__(self, world):
        self.world = world

    def plan(self, state, predictor, value, budget, rng):
        actions = self.world.legal_actions(state)
        best = max(actions, key=lambda a: abs(a.x))
        return Decision(best, 1.0, Spend(predictor_calls=0))


@pytest.mark.parametrize("rows, stable", [
    ([(1.2, 0, 0), (1.2, 0, 1), (0.6, 0, 2)], True),          # centred stack
    ([(0.6, 0, 0), (1.8, 0.2, 1)], True),                     # centre of mass over the base
    ([(0.6, 0, 0), (1.8, 0.8, 1)], False),                    # centre of mass past the base's edge
    ([(1.8, 0, 0), (1.8, 0.7, 1), (1.8, 1.4, 2)], False),     # staircase: top two past the edge
    ([(0.6, 0, 0), (1.8, 0.45, 1)], False),                   # a cantilever alone falls ...
    ([(0.6, 0, 0), (1.8, 0.45, 1), (1.2, -0.15, 2)], True),   # ... a counterweight above holds it
])
def test_known_towers(models, rows, stable):
    assert models["world"].is_stable(Geometry.from_tuples(rows)) is stable


def test_collapse_ends_the_episode_with_zero_reward(models):
    task = Task("t", (0.6, 1.8, 1.2, 1.2))
    record = run_episode(task, models["world"], models["predictor"], Reckless(models["world"]),
                         models["value"], episode_rng(0, 0, 0))
    assert len(record["steps"]) == 1 and record["steps"][0]["stable"] is False
    assert record["stable_throughout"] is False and record["reward"] == 0.0
    assert record["overhang"] > 1.0


def test_myopic_with_veridical_never_collapses(models):
    task = Task("t", (1.2, 1.8, 0.6, 1.2))
    record = run_episode(task, models["world"], models["predictor"], models["planner"],
                         models["value"], episode_rng(0, 0, 0))
    assert record["stable_throughout"] and len(record["steps"]) == 3
    assert record["reward"] == pytest.approx(record["overhang"]) and record["reward"] > 1.2
    overhangs = [s["overhang"] for s in record["steps"]]
    assert overhangs == sorted(overhangs)


def test_episode_generators_are_independent_of_order():
    a = episode_rng(5, 3, 1).random(4)
    assert np.array_equal(a, episode_rng(5, 3, 1).random(4))
    assert not np.array_equal(a, episode_rng(5, 1, 3).random(4))
