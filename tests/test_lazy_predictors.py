"""Lazy answers of the IPE, the CNN and the hybrid (``lazy: true``): the same scores as eager answers, from
fewer towers in deep searches."""

import numpy as np
import pytest

from overhang_framework.fit.scores import Model
from overhang_framework.interfaces import Budget, Task
from overhang_framework.plugins import Registry
from overhang_framework.search import Expander, root_scores

from search_fixtures import value, world  # noqa: F401  (the shared static world and its value)

REG = Registry()


def walk(world, widths, placed, seed):
    """A state of ``placed`` blocks put down at random among the placements the static physics keeps standing."""
    rng = np.random.default_rng(seed)
    state = world.initial_state(Task("t", widths))
    for _ in range(placed):
        actions = world.legal_actions(state)
        standing = [a for a in actions if world.is_stable(world.successor(state, a).geometry)]
        state = world.step(state, standing[rng.integers(len(standing))])
    return state


STATES = [((1.2, 1.8, 0.6, 1.2, 0.6, 1.8), 1, 0), ((0.6, 1.2, 1.2, 0.6, 1.8, 0.6), 2, 1),
          ((1.8, 0.6, 0.6, 1.2, 1.2, 0.6), 3, 2), ((1.2, 1.2, 0.6, 0.6, 1.8, 1.2), 2, 3)]


@pytest.mark.parametrize("sigma", [0.01, 0.03, 0.08])
def test_the_ipe_settles_any_subset_of_candidates_as_predict_scores_them(world, sigma):
    eager = REG.create("predictor", {"name": "ipe", "K": 20, "sigma": sigma}, world=world)
    lazy = REG.create("predictor", {"name": "ipe", "K": 20, "sigma": sigma, "lazy": True}, world=world)
    pick = np.random.default_rng(7)
    checked = 0
    for n, (widths, placed, seed) in enumerate(STATES):
        state = walk(world, widths, placed, seed)
        actions = world.legal_actions(state)
        want = eager.predict(state, actions, np.random.default_rng(n))
        p, settle, classify = lazy.predict_lazy(state, actions, np.random.default_rng(n))
        assert np.isnan(p).all() and (np.asarray(classify(range(len(actions)))) == -1).all()
        # subsets in a random order, as a search settles them, then the rest
        order = pick.permutation(len(actions))
        for part in np.array_split(order, 3):
            np.testing.assert_array_equal(settle(list(part)), want[part])
            checked += len(part)
        # near-critical candidates (strictly between falling and standing in every draw) are among them
    assert checked > 60


def test_the_ipe_remembers_lazy_answers_and_gives_them_back_without_simulating(world):
    lazy = REG.create("predictor", {"name": "ipe", "K": 10, "lazy": True}, world=world)
    lazy.remember(100)
    state = walk(world, (1.2, 1.8, 0.6, 1.2), 1, 0)
    actions = world.legal_actions(state)
    _, settle, _ = lazy.predict_lazy(state, actions, np.random.default_rng(3))
    first = settle([0, 2])
    _, settle_again, classify = lazy.predict_lazy(state, actions, np.random.default_rng(3))
    known = np.asarray(classify([0, 1, 2]))
    np.testing.assert_array_equal(known[[0, 2]], first)
    assert known[1] == -1
    assert lazy.stats()["remembered"] == 1


@pytest.fixture(scope="module")
def networks(world):
    return {lazy: REG.create("predictor", {"name": "cnn", "lazy": lazy}, world=world) for lazy in (False, True)}


# depth 3 with the networks (24 s and 19 s on a busy machine) runs with the slow tests; depth 2 covers their code
@pytest.mark.parametrize("depth,family", [
    (2, "ipe"), (2, "cnn"), (2, "hybrid"), (3, "ipe"),
    pytest.param(3, "cnn", marks=pytest.mark.slow), pytest.param(3, "hybrid", marks=pytest.mark.slow)],
    ids=lambda v: str(v))
def test_a_lazy_search_gives_the_eager_search_scores(world, value, family, depth, networks):
    """Every root score of the planner's exact (softmax) search, lazy against eager, on states of 2 to 4 blocks."""
    def make(lazy):
        if family == "cnn":
            return networks[lazy]
        if family == "ipe":
            return REG.create("predictor", {"name": "ipe", "K": 10, "lazy": lazy}, world=world)
        return REG.create("predictor", {"name": "hybrid", "switch": 4, "early_params": {"K": 10, "lazy": lazy},
                                        "late_params": {"lazy": lazy}}, world=world)

    eager, lazy = make(False), make(True)
    for n, (widths, placed, seed) in enumerate(STATES[:1] if depth == 3 else STATES):
        state = walk(world, widths[: placed + 1 + depth], placed, seed)
        scores, towers = {}, {}
        for label, predictor in (("eager", eager), ("lazy", lazy)):
            getattr(predictor, "clear_cache", lambda: None)()
            before = predictor.stats().get("towers", 0)
            expander = Expander(world, predictor, Budget(), seed=n)
            scores[label] = root_scores(expander, value, state, depth, True, prefetch=True)
            towers[label] = predictor.stats().get("towers", 0) - before
        np.testing.assert_array_equal(scores["lazy"], scores["eager"])
        if family == "cnn" and depth == 3:  # the leaves it need not score: fewer towers through the network
            assert towers["lazy"] < 0.7 * towers["eager"], towers


def test_only_cheap_lazy_predictors_settle_a_node_at_once(world):
    veridical = REG.create("predictor", {"name": "veridical"}, world=world)
    assert Expander(world, veridical, Budget(), seed=0).settle_batch == 1
    assert not Expander(world, veridical, Budget(), seed=0).settle_inner
    ipe = REG.create("predictor", {"name": "ipe", "K": 5, "lazy": True, "settle_batch": 8}, world=world)
    assert Expander(world, ipe, Budget(), seed=0).settle_batch == 8
    hybrid = REG.create("predictor", {"name": "hybrid", "early_params": {"lazy": True}}, world=world)
    assert hybrid.predict_lazy is not None and hybrid.settle_inner
    assert REG.create("predictor", {"name": "hybrid", "late_params": {"lazy": False}},
                      world=world).predict_lazy is None
    # lazy: auto (the CNN's default) is asked lazily only by a search without a budget, and never by a table
    auto = REG.create("predictor", {"name": "hybrid"}, world=world)
    explicit = REG.create("predictor", {"name": "hybrid", "early_params": {"lazy": True},
                                        "late_params": {"lazy": False}}, world=world)
    assert auto.predict_lazy is not None and auto.lazy_auto and hybrid.lazy_auto and not explicit.lazy_auto
    assert Expander(world, auto, Budget(), seed=0).asks_lazily
    assert not Expander(world, auto, Budget(predictor_calls=16), seed=0).asks_lazily
    assert not Expander(world, auto, Budget(seconds=5.0), seed=0).asks_lazily
    assert not Expander(world, auto, Budget(), seed=0, auto_lazy=False).asks_lazily
    assert Expander(world, explicit, Budget(predictor_calls=16), seed=0).asks_lazily  # lazy: true is always
    assert not Expander(world, hybrid, Budget(predictor_calls=16), seed=0).asks_lazily  # a part is auto
    # a part that is lazy of itself (the tiered world's veridical verdicts) answers eagerly inside a hybrid,
    # as it always has: only parts asked to be lazy are
    tiered = REG.create("world", {"name": "overhang"})
    plain = REG.create("predictor", {"name": "hybrid", "early": "veridical", "late_params": {"lazy": False}},
                       world=tiered)
    assert plain.early.predict_lazy is not None and plain.predict_lazy is None
    mixed = REG.create("predictor", {"name": "hybrid", "early": "veridical", "late_params": {"lazy": True}},
                       world=tiered)
    early_state = tiered.initial_state(Task("t", (1.2, 0.6, 0.6)))
    assert mixed.predict_lazy is not None and not mixed.lazy_for(early_state)
    assert mixed.settle_batch == 16 and mixed.settle_inner
    p, settle, classify = mixed.predict_lazy(early_state, tiered.legal_actions(early_state)[:3],
                                             np.random.default_rng(0))
    assert settle is None and not np.isnan(p).any()  # the veridical part answered whole


@pytest.mark.parametrize("name,params,words", [
    ("ipe", {"lazy": "yes"}, "lazy must be true or false"),
    ("ipe", {"settle_batch": 0}, "settle_batch must be a whole number >= 1"),
    ("cnn", {"lazy": 1}, "lazy must be true, false or auto, got 1"),
    ("cnn", {"settle_batch": 2.5}, "settle_batch must be a whole number >= 1"),
    ("cnn", {"lazy": True, "runtime": "torch"}, "lazy needs a tower's answer to be the same in any batch"),
])
def test_bad_lazy_settings_are_refused(world, name, params, words):
    with pytest.raises(Exception, match=words):
        REG.create("predictor", {"name": name, **params}, world=world)


def test_how_answers_are_asked_for_leaves_a_models_tables_where_they_were():
    context = {"world": {}, "value": {"name": "overhang"}}
    plain = Model({"name": "hybrid", "early_params": {"K": 50}, "late_params": {}}, 2)
    lazy = Model({"name": "hybrid", "early_params": {"K": 50, "lazy": True, "settle_batch": 4},
                  "late_params": {"lazy": True}}, 2)
    assert plain.key(context) == lazy.key(context)
    assert plain.draw_seed(context) == lazy.draw_seed(context)


def test_a_run_made_before_the_lazy_setting_continues_and_one_asking_for_it_is_refused(tmp_path):
    from overhang_framework.rundir import RunDir, RunDirError

    before = {"predictor": {"name": "ipe", "K": 50}, "seed": 0}
    RunDir(tmp_path / "run").prepare(before)
    now = {"predictor": {"name": "ipe", "K": 50, "lazy": False, "settle_batch": 16}, "seed": 0}
    RunDir(tmp_path / "run").check_config(now)  # what the run did: the same config
    with pytest.raises(RunDirError, match=r"predictor.lazy: \(unset\) -> true"):
        RunDir(tmp_path / "run").check_config({**now, "predictor": {**now["predictor"], "lazy": True}})


@pytest.mark.parametrize("choice", ["argmax", pytest.param("softmax", marks=pytest.mark.slow)])
def test_the_cnns_automatic_laziness_keeps_every_decision_and_charge(world, choice):
    """lazy: auto, the default, asks lazily in an unbudgeted search: the same decisions, scored with fewer
    towers; under a call budget it asks as eagerly as lazy: false, charged the same calls."""
    from overhang_framework.interfaces import Task

    planner = REG.create("planner", {"name": "lookahead", "depth": 3, "choice": choice, "beta": 3.0}, world=world)
    value = REG.create("value", {"name": "overhang"}, world=world)
    models = {lazy: REG.create("predictor", {"name": "cnn", "lazy": lazy}, world=world) for lazy in ("auto", False)}
    state = world.initial_state(Task("t", (1.2, 1.8, 0.6, 1.2)))
    for budget in (lambda: Budget(), lambda: Budget(predictor_calls=12)):
        decided, towers = {}, {}
        for lazy, predictor in models.items():
            predictor.clear_cache()
            before = predictor.stats()["towers"]
            d = planner.plan(state, predictor, value, budget(), np.random.default_rng(4))
            decided[lazy] = (d.action, d.choice_probability, d.spend.predictor_calls, d.spend.depth_completed)
            towers[lazy] = predictor.stats()["towers"] - before
        assert decided["auto"] == decided[False]
        if budget().limited:
            assert towers["auto"] == towers[False]
        else:
            assert towers["auto"] < towers[False]
