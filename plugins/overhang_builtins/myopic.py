"""The myopic planner: the paper's ``argmax_a p(s, a) * r(s, a)``, with ``r`` the overhang after the action."""

from __future__ import annotations

import time

import numpy as np

from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, State, Value, World
from overhang_framework.search import ChoiceRule, Expander, settled_scores


class MyopicPlanner(Planner):
    """Scores every legal action by ``p(s, a) * r(s, a)`` in one batched predictor call.

    ``choice`` is ``argmax`` (ties broken uniformly at random with the
    episode's generator, so a seed fixes the choice) or ``softmax`` with
    inverse temperature ``beta``. The value plugin is not used: the immediate
    reward is the overhang after the action, as in the paper.
    """

    def __init__(self, world: World, choice: str = "argmax", beta: float = 10.0):
        self.world = world
        self.rule = ChoiceRule(choice, beta)

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        expander = Expander(self.world, predictor, budget, seed=int(rng.integers(2**63)))
        expansion = expander.expand(state, force=True)
        if not expansion.actions:
            raise RuntimeError("no legal action in this state")
        scores = settled_scores(expansion, expansion.overhang, exact_all=self.rule.needs_all_scores,
                                batch=expander.settle_batch)
        choice = self.rule.choose(scores, rng)
        spend = expander.stats.spend(time.perf_counter() - start, budget, depth_completed=1)
        return Decision(expansion.actions[choice.index], expansion.p_at(choice.index), spend,
                        choice.probability, choice.rank)
