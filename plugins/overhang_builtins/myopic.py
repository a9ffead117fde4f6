"""The myopic planner: argmax over legal actions of predicted stability times immediate overhang."""

from __future__ import annotations

import time

import numpy as np

from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, Spend, State, Value, World


class MyopicPlanner(Planner):
    """``argmax_a p(s, a) * r(s, a)`` with ``r`` the overhang after the action.

    Ties are broken uniformly at random with the decision's generator, so a
    seed fixes the choice.
    """

    def __init__(self, world: World):
        self.world = world

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        actions = self.world.legal_actions(state)
        if not actions:
            raise RuntimeError("no legal action in this state")
        p = np.asarray(predictor.predict(state, actions, rng), dtype=float)
        r = np.array([self.world.overhang(self.world.successor(state, a).geometry) for a in actions])
        score = p * r
        best = np.flatnonzero(np.isclose(score, score.max(), rtol=0, atol=1e-12))
        i = int(best[rng.integers(len(best))]) if len(best) > 1 else int(best[0])
        spend = Spend(predictor_calls=1, actions_scored=len(actions), nodes_expanded=len(actions),
                      seconds=time.perf_counter() - start,
                      budget_exhausted=budget.exhausted())
        return Decision(actions[i], float(p[i]), spend)
