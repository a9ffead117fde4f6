"""The optimal planner: the best achievable reward over the discretised action set, proved by search."""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, Spend, State, Value, World
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

    With the veridical predictor on the world's own physics, a state on an
    optimal path stored by ``python -m overhang_framework.optimum`` (same
    physics and resolution) is answered from that file without searching
    (``stored: false`` always searches).
    """

    def __init__(self, world: World, mirror: bool = True, stored: bool = True):
        for name, flag in (("mirror", mirror), ("stored", stored)):
            if not isinstance(flag, bool):
                raise ValueError(f"{name} must be true or false, got {flag!r}")
        self.world = world
        self.mirror = mirror
        self.stored = stored
        self.rule = ChoiceRule("argmax")
        self._moves: Optional[dict] = None

    def _stored_move(self, state: State, predictor: Predictor):
        if not self.stored or not getattr(predictor, "world_verdicts", False):
            return None
        if self._moves is None:
            from overhang_framework.optimum import optimal_moves

            self._moves = optimal_moves(self.world)
        from overhang_framework.search import state_key

        return self._moves.get(state_key(state))

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        stored = self._stored_move(state, predictor)
        if stored is not None:
            p = float(np.asarray(predictor.predict(state, [stored], rng))[0])
            return Decision(stored, p, Spend(predictor_calls=1, actions_scored=1, seconds=time.perf_counter() - start,
                                             depth_completed=len(state.remaining)))
        search = OptimumSearch(self.world, predictor, seed=int(rng.integers(2**63)), mirror=self.mirror,
                               budget=budget)
        scores = search.root_scores(state)
        choice = self.rule.choose(scores, rng)
        expansion = search.expander.expand(state, force=True)
        spend = search.expander.stats.spend(time.perf_counter() - start, budget,
                                            depth_completed=len(state.remaining))
        return Decision(expansion.actions[choice.index], expansion.p_at(choice.index), spend,
                        choice.probability, choice.rank)
