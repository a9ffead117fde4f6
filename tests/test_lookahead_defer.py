"""Lookahead with the world's verdicts runs the reference for an unsure tower only when its subtree could
change the choice (``planner.defer``), and chooses as when it settles every such tower first."""

from __future__ import annotations

import numpy as np
import pytest

from overhang_framework.interfaces import Budget, Task
from overhang_framework.plugins import Registry
from overhang_framework.search import Expander, root_scores, ties

from test_lazy_search import HidingWorld, random_states

REG = Registry()


def decide(world, state, depth, choice, defer, budget=None, seed=5):
    predictor = REG.create("predictor", {"name": "veridical"}, world=world)
    value = REG.create("value", {"name": "overhang"}, world=world)
    planner = REG.create("planner", {"name": "lookahead", "depth": depth, "choice": choice, "beta": 4.0,
                                     "defer": defer}, world=world)
    d = planner.plan(state, predictor, value, budget or Budget(), np.random.default_rng(seed))
    return d.action, d.choice_probability, d.spend.depth_completed, d.spend.predictor_calls


@pytest.mark.parametrize("depth, choice", [(2, "argmax"), (2, "softmax"),
                                           pytest.param(3, "argmax", marks=pytest.mark.slow),
                                           pytest.param(3, "softmax", marks=pytest.mark.slow)])
def test_deferred_settling_chooses_as_settling_first_with_fewer_reference_runs(depth, choice):
    revealed = {True: 0, False: 0}
    for state in random_states(5 if depth == 3 else 8, seed=10 + depth):
        got = {}
        for defer in (True, False):
            world = HidingWorld()
            got[defer] = decide(world, state, depth, choice, defer)[:3]
            revealed[defer] += world.revealed
        assert got[True] == got[False]
    assert revealed[True] <= revealed[False], revealed
    if choice == "argmax" or depth == 3:  # softmax at depth 2 needs every root answer and every leaf's
        assert revealed[True] < revealed[False], revealed


@pytest.mark.parametrize("depth", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_deferred_root_scores_keep_the_best_the_ties_and_every_softmax_score(depth):
    """Deferred (with the lattice step in the subtrees, as argmax plans) against settling first."""
    from overhang_framework.search import lattice_step

    for state in random_states(6, seed=20 + depth):
        argmax, exact = {}, {}
        for defer in (True, False):
            world = HidingWorld()
            predictor = REG.create("predictor", {"name": "veridical"}, world=world)
            value = REG.create("value", {"name": "overhang"}, world=world)
            step = lattice_step(world, predictor, value, state) if defer else 0.0
            assert not defer or step == pytest.approx(0.1) or step > 0
            scores = root_scores(Expander(world, predictor, Budget(), seed=1), value, state, depth, False,
                                 defer=defer, step=step)
            argmax[defer] = (sorted(ties(scores).tolist()), round(float(scores.max()), 12))
            exact[defer] = root_scores(Expander(world, predictor, Budget(), seed=1), value, state, depth, True,
                                       defer=defer)
        assert argmax[True] == argmax[False]
        np.testing.assert_array_equal(exact[True], exact[False])


def test_under_a_budget_the_search_settles_as_before():
    """Deferring would change which calls a budgeted search is charged, so a budget turns it off."""
    for state in random_states(4, seed=31):
        got = {}
        for defer in (True, False):
            world = HidingWorld()
            got[defer] = (decide(world, state, 3, "argmax", defer, Budget(predictor_calls=20)), world.revealed)
        assert got[True] == got[False]


def watched(world, depth, choice, defer):
    """A lookahead planner on ``world`` whose choice rule keeps the root scores it was given."""
    planner = REG.create("planner", {"name": "lookahead", "depth": depth, "choice": choice, "beta": 4.0,
                                     "defer": defer}, world=world)
    seen, rule_choose = [], planner.rule.choose

    def choose(scores, rng):
        seen.append(np.asarray(scores, dtype=float))
        return rule_choose(scores, rng)

    planner.rule.choose = choose
    return planner, seen


@pytest.mark.parametrize("depth, choice, n", [(2, "argmax", 4), pytest.param(2, "softmax", 4, marks=pytest.mark.slow),
                                              pytest.param(3, "argmax", 2, marks=pytest.mark.slow),
                                              pytest.param(3, "softmax", 4, marks=pytest.mark.slow)])
def test_on_the_tiered_world_the_same_choices_ties_and_scores_with_fewer_reference_runs(depth, choice, n):
    """The default physics, each decision from an empty verdict cache: argmax sees the same tied best actions
    and chooses the same one, softmax the same root scores to the bit; the reference runs no more often."""
    runs = {True: [], False: []}
    for state in random_states(n, seed=40 + depth):
        got = {}
        for defer in (True, False):
            world = REG.create("world", {"name": "overhang"})  # physics: tiered, a fresh verdict cache
            predictor = REG.create("predictor", {"name": "veridical"}, world=world)
            value = REG.create("value", {"name": "overhang"}, world=world)
            planner, seen = watched(world, depth, choice, defer)
            d = planner.plan(state, predictor, value, Budget(), np.random.default_rng(5))
            (scores,) = seen
            got[defer] = (d.action, d.choice_probability, d.choice_rank, scores)
            runs[defer].append(int(world.stats()["cache"]["backend"].get("reference", 0)))
        assert got[True][:3] == got[False][:3]
        if choice == "argmax":
            assert ties(got[True][3]).tolist() == ties(got[False][3]).tolist()
        else:
            np.testing.assert_array_equal(got[True][3], got[False][3])
    assert all(a <= b for a, b in zip(runs[True], runs[False])), runs
    if choice == "argmax" or depth == 3:  # softmax at depth 2 needs every root verdict and every leaf's
        assert sum(runs[True]) < sum(runs[False]), runs


def test_only_dear_answers_are_deferred():
    """The criterion: a lazy predictor that settles one child at a time (the world's verdicts)."""
    tiered = REG.create("world", {"name": "overhang"})
    static = REG.create("world", {"name": "overhang", "physics": "static"})
    cases = {(tiered, "veridical"): True, (static, "veridical"): False,  # static: nothing left unknown
             (HidingWorld(), "veridical"): True}
    for (world, name), dear in cases.items():
        predictor = REG.create("predictor", {"name": name}, world=world)
        assert Expander(world, predictor, Budget(), seed=0).dear_answers is dear
        assert Expander(world, predictor, Budget(predictor_calls=5), seed=0).dear_answers is dear
    ipe = REG.create("predictor", {"name": "ipe", "K": 2, "lazy": True}, world=static)  # settles a node at once
    assert ipe.predict_lazy is not None and not Expander(static, ipe, Budget(), seed=0).dear_answers


def test_a_bad_defer_setting_is_one_line():
    world = REG.create("world", {"name": "overhang", "physics": "static"})
    with pytest.raises(ValueError, match="defer must be true or false, got 'sometimes'"):
        REG.create("planner", {"name": "lookahead", "defer": "sometimes"}, world=world)


def test_the_benchmark_compares_decisions_and_counts_reference_runs(capsys):
    from overhang_framework.bench.lookahead_defer import main

    out = main(["--tasks", "1", "--placed", "1", "--depths", "2", "--seed", "2"])
    row = out["depths"][2]
    assert out["states"] == 1 and row["same_decisions"] == 1
    assert row["deferred"]["reference_runs_per_decision"] <= row["settled first"]["reference_runs_per_decision"]
    assert "the same decision in 1 of 1" in capsys.readouterr().out
