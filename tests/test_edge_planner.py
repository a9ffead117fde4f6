"""The edge heuristic: no predictor, no look-ahead, a local rule of support (planner=edge)."""

import numpy as np
import pytest

from overhang_builtins.edge import locally_supported
from overhang_framework.geometry import Block, Geometry
from overhang_framework.interfaces import Action, Budget, State, Task
from overhang_framework.plugins import Registry

from search_fixtures import veridical, world  # noqa: F401

SEQUENCE = (1.2, 0.6, 0.6, 1.2, 0.6, 0.6)


class Refuses:
    """A predictor the heuristic must never ask."""

    def predict(self, *args, **kwargs):
        raise AssertionError("the edge heuristic asked a predictor")

    predict_batch = predict


def test_the_local_rule_looks_only_at_the_blocks_directly_underneath():
    state = State(Geometry((Block(1.2, 0.0, 0), Block(0.6, 0.5, 1))), (0.6,))
    # over the 0.6 block at 0.5 (it spans 0.2 to 0.8): inside, with and without a margin
    assert locally_supported(state, Action(0.7, 2), 0.6)
    assert not locally_supported(state, Action(0.7, 2), 0.6, margin=0.15)
    # its centre beyond the block under it: not supported, though the block overlaps it
    assert not locally_supported(state, Action(0.9, 2), 0.6)
    # on the ground block, whatever the block above it weighs
    assert locally_supported(state, Action(-0.5, 1), 0.6)


def test_it_reaches_to_its_margin_and_asks_no_predictor(world):
    planner = Registry().create("planner", {"name": "edge", "margin": 0.1}, world=world)
    state = world.initial_state(Task("t", SEQUENCE))
    decision = planner.plan(state, Refuses(), None, Budget(), np.random.default_rng(0))
    assert decision.spend.predictor_calls == 0
    # a 0.6 block on the 1.2 ground block (edges at +-0.6): its centre 0.1 inside an edge, the farthest such
    assert abs(abs(decision.action.x) - 0.5) < 1e-9 and decision.action.layer == 1


def test_it_builds_what_a_model_of_the_tower_would_not(world, veridical):
    """Outside the fitted models' space: on the first two placements of a task the heuristic's second block stands
    on its own support, but the tower falls, where the veridical myopic planner keeps it standing."""
    edge = Registry().create("planner", {"name": "edge"}, world=world)
    myopic = Registry().create("planner", {"name": "myopic"}, world=world)
    fell = {}
    for name, planner in (("edge", edge), ("myopic", myopic)):
        state = world.initial_state(Task("t", SEQUENCE))
        rng = np.random.default_rng(1)
        for _ in range(2):
            state = world.step(state, planner.plan(state, veridical, None, Budget(), rng).action)
        fell[name] = not world.is_stable(state.geometry)
    assert fell == {"edge": True, "myopic": False}


@pytest.mark.parametrize("margin", [-0.1, 0.3, "0.1", True])
def test_a_bad_margin_is_one_clear_error(world, margin):
    with pytest.raises(Exception, match="margin must be a number of metres from 0 to below 0.3"):
        Registry().create("planner", {"name": "edge", "margin": margin}, world=world)
