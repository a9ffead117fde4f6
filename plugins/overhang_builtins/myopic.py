"""The myopic planner: the paper's ``argmax_a p(s, a) * r(s, a)``, with ``r`` the overhang after the action."""

from __future__ import annotations

import time

import numpy as np

from overhang_framework.geometry import overhang
from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, State, Value, World
from overhang_framework.search import ChoiceRule, Expander, check_risk, settled_scores


class MyopicPlanner(Planner):
    """Scores every legal action by ``p(s, a) * r(s, a)`` in one batched predictor call.

    ``choice`` is ``argmax`` (ties broken uniformly at random with the
    episode's generator, so a seed fixes the choice) or ``softmax`` with
    inverse temperature ``beta``. The value plugin is not used. ``reward``
    says what the immediate reward ``r`` is, that is, how the blocks still to
    come are treated:

    - ``overhang`` (default): the overhang after the action, as in the paper;
    - ``gain``: how much the action adds to the overhang (0 for an action that
      does not extend it, whatever its risk);
    - ``final``: the episode's reward only, so 0 before the last block and
      every earlier action ties (chosen at random).

    ``risk`` (0, the paper's, is risk-neutral) scores an action by ``w(p) * r`` with ``w`` the weight of
    :func:`~overhang_framework.search.risk_weight` (``risk_form``: ``power`` or ``cvar``).
    """

    REWARDS = ("overhang", "gain", "final")

    def __init__(self, world: World, choice: str = "argmax", beta: float = 10.0, reward: str = "overhang",
                 risk: float = 0.0, risk_form: str = "power"):
        if reward not in self.REWARDS:
            raise ValueError(f"unknown myopic reward {reward!r}; allowed: {', '.join(self.REWARDS)}")
        self.world = world
        self.rule = ChoiceRule(choice, beta)
        self.reward = reward
        self.risk = check_risk(risk, risk_form)
        self.risk_form = risk_form

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        expander = Expander(self.world, predictor, budget, seed=int(rng.integers(2**63)), risk=self.risk,
                            risk_form=self.risk_form)
        expansion = expander.expand(state, force=True)
        if not expansion.actions:
            raise RuntimeError("no legal action in this state")
        scores = settled_scores(expansion, self.immediate(state, expansion.overhang), exact_all=self.rule.needs_all_scores,
                                batch=expander.settle_batch)
        choice = self.rule.choose(scores, rng)
        spend = expander.stats.spend(time.perf_counter() - start, budget, depth_completed=1)
        return Decision(expansion.actions[choice.index], expansion.stability_at(choice.index), spend,
                        choice.probability, choice.rank)

    def immediate(self, state: State, after: np.ndarray) -> np.ndarray:
        """The immediate reward ``r`` of each action, from the overhangs ``after`` the actions."""
        if self.reward == "gain":
            return np.maximum(np.asarray(after, dtype=float) - overhang(state.geometry), 0.0)
        if self.reward == "final" and len(state.remaining) > 1:
            return np.zeros(len(after))
        return np.asarray(after, dtype=float)
