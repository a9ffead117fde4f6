"""The hybrid's switch point as a fitted parameter: its grid, draws shared across switch points, answers
remembered without changing a number, and the fit reporting it."""

from __future__ import annotations

import numpy as np
import pytest

from overhang_framework.errors import ConfigError
from overhang_framework.fit.fitting import fit_index, map_placements
from overhang_framework.fit.run import Predictors
from overhang_framework.fit.scores import Model, ScoreTables, share_tables
from overhang_framework.fit.space import model_space
from overhang_framework.geometry import Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import Registry
from overhang_framework.search import node_rng

CONTEXT = {"world": {"name": "overhang", "physics": "static"}, "value": {"name": "overhang"}}
HYBRID = {"predictor": "hybrid", "late": "veridical", "early_params": {"K": 10}}

from search_fixtures import value, world  # noqa: E402,F401  (shared fixtures: the static world of CONTEXT)


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
    # a model without a switch has no such mark in its key
    from overhang_framework.fit.scores import (ENGINE_KEYS, _digest, _strip, code_identity, content_identity,
                                               physics_identity)

    def before(model):
        data = {"predictor": _strip(dict(model.predictor), ENGINE_KEYS), "depth": model.depth,
                "context": _strip(CONTEXT, ENGINE_KEYS), "code": code_identity(model.predictor),
                "physics": physics_identity(CONTEXT)}
        if content_identity(model.predictor):
            data["content"] = content_identity(model.predictor)
        return _digest(data)

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
    # one generator asked twice in one batch: the second question is asked with the draws the first left
    requests = [(STATES[2], world.legal_actions(STATES[2]))] * 2
    for _ in range(2):
        shared, alone = node_rng(9, ("y",)), node_rng(9, ("y",))
        got = remembering.predict_many(requests, [shared, shared])
        want = plain.predict_many(requests, [alone, alone])
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
        assert shared.random() == alone.random()
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


def test_the_models_of_one_ipe_at_every_depth_and_risk_ask_it_once_and_give_the_tables_computed_alone(world, value):
    space = model_space({"ipe": {"predictor": "ipe", "K": 10, "sigma": 0.04, "risk": [0.0, 0.5, 0.9]}}, [1, 2])
    models = [m for index in space for m in index.variants]
    assert len(models) == 6
    registry = Registry()
    shared = Predictors(registry, world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for m in models]
    assert len({id(t.predictor) for t in tables}) == 1
    together = {(t.model.depth, t.model.risk): [t.table(s) for s in STATES] for t in tables}
    counts = tables[0].predictor.stats()
    # the first depth-2 model simulates; every other model's questions are remembered answers
    alone = {}
    for m in models:
        fresh = ScoreTables(world, value, registry.create("predictor", dict(m.predictor), world=world), m, CONTEXT)
        alone[(m.depth, m.risk)] = [fresh.table(s) for s in STATES]
        first = fresh.predictor.stats()["calls"]
    assert counts["calls"] - counts["remembered"] == first
    for key, scores in together.items():
        for got, want in zip(scores, alone[key]):
            np.testing.assert_array_equal(got, want)
    # risk changes the depth-2 tables, so the remembered answers are weighed anew by each model
    assert any(not np.array_equal(a, b) for a, b in zip(together[(2, 0.0)], together[(2, 0.9)]))


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
    assert fit.k == 3 and fit.switch == 2 and fit.row()["switch"] == 2
    single = fit_index("p", "c", variants[:1], map_placements(world, placements))
    assert single.k == 2 and single.switch == 2


# a simulated cohort fitted over every switch point (42 s on a busy machine); the switch's fits on known tables stay in the default suite
@pytest.mark.slow
def test_the_switch_point_of_simulated_hybrid_participants_is_recovered_within_one_stage(tmp_path):
    """Myopic hybrids (IPE early, CNN late) with switch points 3 or 5 (five participants), 8 tasks each: the fit over every
    switch point the tasks allow finds each participant's within one stage. The IPE has the default K = 50: with
    K = 20 the fit's draws and the participants' differ enough that one participant of 5 was fitted three stages
    off (1.4 nats between the two switch points)."""
    import subprocess
    import sys

    import pandas as pd
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config(["predictor=hybrid", "world.physics=static", "progress=false",
                          "cohort.participants.time_limited=0", "cohort.participants.unconstrained=5",
                          "cohort.n_tasks=8"], config_name=CONFIG_NAME)
    OmegaConf.set_struct(cfg, False)
    cfg.predictor.early_params = {"K": 50}
    cfg.cohort.parameters = {"depth": {"dist": "fixed", "value": 1}, "beta": {"dist": "fixed", "value": 20.0},
                             "lapse": {"dist": "fixed", "value": 0.02},
                             "switch": {"dist": "categorical", "values": [3, 5], "p": [0.5, 0.5]}}
    run(cfg, tmp_path / "sim")
    truth = pd.read_csv(tmp_path / "sim" / "participants.csv").set_index("id")["switch"]
    assert set(truth) == {3, 5}
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(tmp_path / "sim" / "log.jsonl"),
                           "--out", str(tmp_path / "fit"), "~models.ipe", "~models.cnn",
                           "+models.hybrid.early_params={K: 50}", "depths=[1]", "world.physics=static",
                           f"cache={tmp_path / 'scores.sqlite'}", "progress=false", "pooled=false"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    fits = pd.read_csv(tmp_path / "fit" / "fits.csv").set_index("participant")
    assert (fits["k"] == 3).all()
    error = (fits["switch"] - truth.reindex(fits.index)).abs()
    assert (error <= 1).all(), pd.DataFrame({"true": truth, "fitted": fits["switch"]})
    assert "fitted switch" in (tmp_path / "fit" / "comparison.md").read_text()


def test_a_cohort_draws_whole_switch_points_only_and_writes_them_only_when_drawn():
    from overhang_framework.behaviour.participants import cohort_from_config, draw_participants, participants_csv

    base = {"name": "c", "participants": {"un": 3}, "parameters": {"lapse": {"dist": "beta", "a": 1.0, "b": 30.0},
                                                                   "beta": {"dist": "lognormal", "median": 10.0,
                                                                            "sigma": 0.5}},
            "decision_time": {"t0": 2.0, "per_call": 0.07, "noise": 0.3}, "motor": {"sd": 0.02, "retries": 5}}
    conditions = {"un": {}}
    plain = draw_participants(cohort_from_config(base, conditions), 0)
    assert participants_csv(plain).splitlines()[0] == "id,index,condition,sigma,depth,beta,lapse"
    assert len({p.lapse for p in plain}) == 3  # drawn, so a draw before them would change them
    drawn = {**base, "parameters": {**base["parameters"], "switch": {"dist": "categorical", "values": [2, 6],
                                                                     "p": [0.5, 0.5]}}}
    people = draw_participants(cohort_from_config(drawn, conditions), 0)
    assert {p.switch for p in people} <= {2, 6} and participants_csv(people).splitlines()[0].endswith(",switch")
    # drawing the switch point leaves every other draw as it was
    assert [(p.lapse, p.beta) for p in people] == [(p.lapse, p.beta) for p in plain]
    bad = {**base, "parameters": {"switch": {"dist": "uniform", "low": 2, "high": 6}}}
    with pytest.raises(ConfigError, match="switch must give whole numbers"):
        cohort_from_config(bad, conditions)


def test_the_models_of_a_process_share_its_search_memory(world, value):
    from overhang_framework.fit.scores import MEMO_NODES, share_memory

    space = model_space({"hybrid": {**HYBRID, "switch": "all"}}, [1, 2], blocks=6)
    shared = Predictors(Registry(), world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for i in space for m in i.variants]
    share_memory(tables)
    assert len(tables) == 12 and {t.memo_limit for t in tables} == {MEMO_NODES // 12}
    share_memory(tables, nodes=1_000)
    assert {t.memo_limit for t in tables} == {2_000}


def test_switch_points_that_give_the_same_numbers_in_a_state_share_one_table(world, value, monkeypatch):
    from overhang_framework import parallel
    from overhang_framework.fit import run

    space = model_space({"hybrid": {**HYBRID, "switch": "all"}, "veridical": {"predictor": "veridical"}}, [1, 2],
                        blocks=4)
    registry = Registry()
    shared = Predictors(registry, world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for i in space for m in i.variants]
    share_tables(tables)
    grid = {t.model.switch for t in tables} - {None}
    assert grid == {2, 3, 4, 5}
    # what the fit hands its workers: per state and depth, the veridical model's table (every tower to the late
    # part) and one per switch point from n + 2 to n + D + 1 (of the grid); not one per switch point
    want = sum(1 + len({n + 2 + k for k in range(d)} & grid) for s in STATES for d in (1, 2)
               for n in [len(s.geometry)])
    seen, totals = {}, []
    monkeypatch.setattr(parallel, "pool_map", lambda setup, args, work, items, jobs, tick: seen.setdefault("i", items) and [])
    run.fill_tables(tables, STATES, jobs=2, on_total=totals.append)
    assert totals == [want] and want < len(tables) * len(STATES)
    together = [[t.table(s) for s in STATES] for t in tables]
    assert sum(t.stats.computed for t in tables) == want
    for t, scores in zip(tables, together):
        alone = ScoreTables(world, value, registry.create("predictor", dict(t.model.predictor), world=world),
                            t.model, CONTEXT)
        for s, got in zip(STATES, scores):
            np.testing.assert_array_equal(got, alone.table(s))
    # a late part whose answers use the draws is no model's table: then each stage computes its own
    noisy = model_space({"hybrid": {"predictor": "hybrid", "late": "ipe", "late_params": {"K": 5},
                                    "early": "veridical", "switch": "all"}}, [1], blocks=4)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for m in noisy[0].variants]
    share_tables(tables)
    for s in STATES:
        n = len(s.geometry)
        assert {id(t.owner(s)) for t in tables} == {id(t) for t in tables if t.model.switch in {n + 1, n + 2}}


def _shared_myopic_tables(world, value, path):
    """The myopic hybrid at every switch point of 4-block tasks and the veridical model (its late part), tables
    shared and cached in ``path``: (space, cache, predictors, tables)."""
    from overhang_framework.fit.scores import ScoreCache

    space = model_space({"hybrid": {**HYBRID, "switch": "all"}, "veridical": {"predictor": "veridical"}}, [1],
                        blocks=4)
    cache = ScoreCache(path)
    shared = Predictors(Registry(), world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT, cache) for i in space for m in i.variants]
    share_tables(tables)
    return space, cache, shared, tables


def test_a_table_computed_for_another_switch_point_is_kept_under_every_models_key(world, value, tmp_path):
    space, cache, shared, tables = _shared_myopic_tables(world, value, tmp_path / "scores.sqlite")
    for t in tables:
        for s in STATES:
            t.table(s)
    assert sum(t.stats.computed for t in tables) < len(tables) * len(STATES)
    # a later run with one switch point alone (a check, a smaller grid) finds every table in the cache
    for model in space[0].variants:
        alone = ScoreTables(world, value, Registry().create("predictor", dict(model.predictor), world=world), model,
                            CONTEXT, cache)
        assert all(alone.known(s) for s in STATES)
        for s in STATES:
            alone.table(s)
        assert alone.stats.computed == 0


def test_only_hybrids_of_the_same_settings_share_and_a_cycle_is_refused(world, value):
    from overhang_framework.errors import OverhangError

    config = model_space({"hybrid": {**HYBRID, "switch": [2, 3]}}, [1])[0].variants
    shared = Predictors(Registry(), world)
    # the same switch points, settings that differ below the top level: no table is shared between them
    a = [ScoreTables(world, value, shared(m.predictor), Model({**m.predictor, "extra": {"switch": 1}}, 1), CONTEXT)
         for m in config]
    b = [ScoreTables(world, value, shared(m.predictor), Model({**m.predictor, "extra": {"switch": 2}}, 1), CONTEXT)
         for m in config]
    share_tables(a + b)
    for s in STATES:
        assert {id(t.owner(s)) for t in a} <= {id(t) for t in a}
        assert {id(t.owner(s)) for t in b} <= {id(t) for t in b}
    first, second = a
    first.same_as = lambda state: second
    second.same_as = lambda state: first
    with pytest.raises(OverhangError, match="point to each other in a cycle"):
        first.owner(STATES[0])


def test_the_check_finds_a_fitted_hybrids_tables_under_the_switch_point_that_computed_them(world, value, tmp_path):
    from overhang_framework.fit import check
    from overhang_framework.fit.scores import ScoreCache

    space, cache, shared, tables = _shared_myopic_tables(world, value, tmp_path / "scores.sqlite")
    for s in STATES:  # only the tables that computed something are in the cache (as a fit's workers leave it)
        for t in tables:
            if t.owner(s) is t:
                t.table(s)
    cache.close()
    spec = {"models": [[i.label, dict(m.predictor)] for i in space for m in i.variants]}
    assert [m.label for m in check.spec_models(spec)] == [i.label for i in space for _ in i.variants]
    fitted = space[0].variants[-1]  # switch point 5: the IPE judges every tower of these states
    env = check._setup(CONTEXT, str(tmp_path / "scores.sqlite"), check.spec_models(spec))
    mine = check._tables(env, fitted)
    assert mine.model == fitted and len(env["tables"]) == len(tables)  # its sibling switch points and the late model
    assert all(mine.known(s) for s in STATES)
    alone = ScoreTables(world, value, shared(fitted.predictor), fitted, CONTEXT, ScoreCache(tmp_path / "scores.sqlite"))
    assert not all(alone.known(s) for s in STATES)  # by its own key alone, some are not found


def test_a_hybrid_draws_as_its_early_part_so_where_every_tower_is_early_its_table_is_that_models(world, value):
    space = model_space({"ipe": {"predictor": "ipe", "K": 10, "sigma": [0.03, 0.05]},
                         "hybrid": {**HYBRID, "switch": "all"}}, [1, 2], blocks=4)
    ipes = {(m.depth, m.sigma): m for i in space if i.family == "ipe" for m in i.variants}
    hybrids = [m for i in space if i.family == "hybrid" for m in i.variants]
    # the early part's settings are the IPE's at sigma 0.03 (the part's default): one seed, whatever the sigma
    assert {m.draw_seed(CONTEXT) for m in [*ipes.values(), *hybrids]} == {ipes[1, 0.03].draw_seed(CONTEXT)}
    other = Model({**hybrids[0].predictor, "early_params": {"K": 12}}, 2)
    assert other.draw_seed(CONTEXT) != hybrids[0].draw_seed(CONTEXT)
    registry = Registry()

    def alone(model, state):
        return ScoreTables(world, value, registry.create("predictor", dict(model.predictor), world=world), model,
                           CONTEXT).table(state)

    # computed alone, a hybrid that sends every tower of its search to the IPE gives the IPE's table to the bit
    compared = 0
    for model in hybrids:
        for s in STATES:
            n = len(s.geometry)
            if model.switch >= n + model.depth + 1:
                np.testing.assert_array_equal(alone(model, s), alone(ipes[model.depth, 0.03], s))
                compared += 1
    assert compared >= 4
    # in a fit such a table is the IPE's, computed once; the others are their own, and equal what they are alone
    shared = Predictors(registry, world)
    tables = [ScoreTables(world, value, shared(m.predictor), m, CONTEXT) for i in space for m in i.variants]
    share_tables(tables)
    by_model = {id(t): t for t in tables}
    for t in tables:
        if t.model.family != "hybrid":
            continue
        assert t.predictor.early is shared(ipes[1, 0.03].predictor)
        for s in STATES:
            n = len(s.geometry)
            owner = t.owner(s)
            if t.model.switch >= n + t.model.depth + 1:
                assert owner.model == ipes[t.model.depth, 0.03] and id(owner) in by_model
            else:
                assert owner.model.family == "hybrid"
            np.testing.assert_array_equal(t.table(s), alone(t.model, s))
