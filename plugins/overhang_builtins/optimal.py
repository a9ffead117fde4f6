"""The optimal planner: the best achievable reward over the discretised action set, proved by search."""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, State, Value, World
from overhang_framework.optimum import OptimumSearch
from overhang_framework.search import ChoiceRule


class OptimalPlanner(Planner):
    """Plays the first action of a sequence that maximises ``prod_k p(s_k, a_k) * overhang(final)``
    over every remaining placement.

    With the veridical predictor (``p`` is 0 or 1) that is the best reward the
    task allows from the current state, over the world's discretised action
    set. The search (:class:`~overhang_framework.optimum.OptimumSearch`) is
    exhaustive with bounds, memoises states by their canonical geometry and
    remaining widths, and treats a tower and its mirror image as one. It uses
    neither the value plugin nor any budget: it is the reference the other
    planners are measured against. Ties among optimal first actions are broken
    with the episode's generator.
    """

    def __init__(self, world: World, mirror: bool = True):
        if not isinstance(mirror, bool):
            raise ValueError(f"mirror must be true or false, got {mirror!r}")
        self.world = world
        self.mirror = mirror
        self.rule = ChoiceRule("argmax")

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        search = OptimumSearch(self.world, predictor, seed=int(rng.integers(2**63)), mirror=self.mirror,
                               budget=budget)
        scores = search.root_scores(state)
        choice = self.rule.choose(scores, rng)
        expansion = search.expander.expand(state, force=True)
        spend = search.expander.stats.spend(time.perf_counter() - start, budget,
                                            depth_completed=len(state.remaining))
        return Decision(expansion.actions[choice.index], float(expansion.p[choice.index]), spend,
                        choice.probability, choice.rank)
