"""The hybrid's switch point as a fitted parameter: its grid, draws shared across switch points, answers
remembered without changing a number, and the fit reporting it."""

from __future__ import annotations

import numpy as np
import pytest

from overhang_framework.errors import ConfigError
from overhang_framework.fit.fitting import fit_index, map_placements
from overhang_framework.fit.run import Predictors
from overhang_framework.fit.scores import Model, ScoreTables
from overhang_framework.fit.space import model_space
from overhang_framework.geometry import Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import Registry
from overhang_framework.search import node_rng

CONTEXT = {"world": {"name": "overhang", "physics": "static"}, "value": {"name": "overhang"}}
HYBRID = {"predictor": "hybrid", "late": "veridical", "early_params": {"K": 10}}


@pytest.fixture(scope="module")
def world():
    return Registry().create("world", CONTEXT["world"])


@pytest.fixture(scope="module")
def value(world):
    return Registry().create("value", CONTEXT["value"], world=world)


def _state(blocks, remaining) -> State:
    return State(Geometry(tuple(Block(float(w), float(x), int(layer)) for w, x, layer in blocks)),
                 tuple(float(w) for w in remaining))


STATES = [_state([[1.2, 0.0, 0]], [0.6, 1.2, 0.6]),
          _state([[1.2, 0.0, 0], [0.6, 0.4, 1]], [1.2, 0.6]),
          _state([[1.8, 0.0, 0], [1.2, -0.5, 1], [0.6, 0.2, 1]], [1.2, 0.6])]


def test_switch_all_spans_every_switch_point_the_tasks_allow():
    space = model_space({"hybrid": {**HYBRID, "switch": "all"}}, [1, 2], blocks=6)
    assert [i.label for i in space] == ["hybrid/myopic", "hybrid/D2"]
    assert [m.switch for m in space[0].variants] == [2, 3, 4, 5, 6, 7]
    assert [m.switch for m in model_space({"hybrid": {**HYBRID, "switch": [5, 3, 3]}}, [1])[0].variants] == [3, 5]
    # a fixed switch point is no grid; the checked space leaves 'all' for when the tasks are known
    assert [m.switch for m in model_space({"hybrid": {**HYBRID, "switch": 5}}, [1])[0].variants] == [5]
    assert len(model_space({"hybrid": {**HYBRID, "switch": "all"}}, [1], check_only=True)[0].variants) == 1


@pytest.mark.parametrize("spec, message", [
    ({"hybrid": {**HYBRID, "switch": 0}}, "switch must be a whole number >= 1"),
    ({"hybrid": {**HYBRID, "switch": [2, 2.5]}}, "switch must be a whole number >= 1"),
    ({"hybrid": {**HYBRID, "switch": "some"}}, "or 'all'"),
    ({"hybrid": {**HYBRID, "switch": "all"}}, "needs the tasks' number of blocks"),
    ({"ipe": {"predictor": "ipe", "switch": [3, 4]}}, "has no setting 'switch'"),
])
def test_a_bad_switch_grid_is_refused_with_what_is_allowed(spec, message):
    with pytest.raises(ConfigError, match=message):
        model_space(spec, [1])


def test_the_switch_point_is_left_out_of_the_draws_but_not_out_of_the_tables_key():
    configs = [m.predictor for m in model_space({"hybrid": {**HYBRID, "switch": [3, 4]}}, [2])[0].variants]
    a, b = Model(configs[0], 2), Model(configs[1], 2)
    assert a.draw_seed(CONTEXT) == b.draw_seed(CONTEXT)
    assert a.key(CONTEXT) != b.key(CONTEXT)
    # the hybrid's key says its draws leave the switch out, so tables keyed before that are not reused;
    # a model without a switch keeps the key it had
    from overhang_framework.fit.scores import ENGINE_KEYS, _digest, _strip

    def before(model):
        return _digest({"predictor": _strip(dict(model.predictor), ENGINE_KEYS), "depth": model.depth,
                        "context": _strip(CONTEXT, ENGINE_KEYS)})

    ipe = Model(model_space({"ipe": {"predictor": "ipe"}}, [2])[0].variants[0].predictor, 2)
    assert ipe.key(CONTEXT) == before(ipe) and a.key(CONTEXT) != before(a)


def test_remembered_answers_are_the_simulated_ones_and_leave_the_generator_where_simulating_would(world):
    registry = Registry()
    plain = registry.create("predictor", {"name": "ipe", "K": 12}, world=world)
    remembering = registry.create("predictor", {"name": "ipe", "K": 12}, world=world)
    remembering.remember(100)
    for state in STATES:
        actions = world.legal_actions(state)
        expected_rng = node_rng(7, ("x",))
        expected = plain.predict(state, actions, expected_rng)
        after = expected_rng.random()
        for _ in range(2):  # simulated, then remembered
            rng = node_rng(7, ("x",))
            got = remembering.predict(state, actions, rng)
            np.testing.assert_array_equal(got, expected)
            assert rng.random() == after
    assert remembering.stats() == {"calls": 2 * len(STATES), "remembered": len(STATES)}
    # other draws are other questions
    remembering.predict(STATES[1], world.legal_actions(STATES[1]), node_rng(8, ("x",)))
    assert remembering.stats()["remembered"] == len(STATES)
    with pytest.raises(ValueError, match="whole number >= 0"):
        remembering.remember(-1)


def test_the_hybrids_of_every_switch_point_share_their_parts_answers_and_give_the_tables_computed_alone(world, value):
    space = model_space({"hybrid": {**HYBRID, "switch": "all"}}, [2], blocks=4)
    registry = Registry()
    shared = Predictors(registry, world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for m in space[0].variants]
    early = {id(t.predictor.early) for t in tables}
    assert len(early) == 1  # one IPE answers every switch point's early towers
    together = [[t.table(s) for s in STATES] for t in tables]
    ipe = tables[0].predictor.early
    assert ipe.stats()["remembered"] > 0
    for model, scores in zip(space[0].variants, together):
        alone = ScoreTables(world, value, registry.create("predictor", dict(model.predictor), world=world), model,
                            CONTEXT)
        for s, got in zip(STATES, scores):
            np.testing.assert_array_equal(got, alone.table(s))
    # the switch changes the tables: every tower to the IPE (5) against every tower to the physics (2)
    assert any(not np.array_equal(a, b) for a, b in zip(together[0], together[-1]))


def test_fit_index_reports_the_switch_point_and_counts_it_as_a_parameter(world, value):
    from overhang_framework.fit.fitting import Placement

    space = model_space({"hybrid": {**HYBRID, "switch": [2, 5]}}, [1])
    shared = Predictors(Registry(), world)
    variants = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for m in space[0].variants]
    placements = []
    for state in STATES:  # choose the physics' best action in every state: the veridical late part fits best
        verdicts = variants[0].table(state)
        action = world.legal_actions(state)[int(np.argmax(verdicts))]
        placements.append(Placement("p", "c", state, action.x, action.layer))
    fit = fit_index("p", "c", variants, map_placements(world, placements))
    assert fit.k == 3 and fit.switch in (2, 5) and fit.row()["switch"] == fit.switch
    single = fit_index("p", "c", variants[:1], map_placements(world, placements))
    assert single.k == 2 and single.switch == 2
