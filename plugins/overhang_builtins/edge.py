"""The edge heuristic: a planner that consults no predictor and looks no step ahead.

It reaches out as far as a local rule of support says it may: a placement counts as safe when the new block's
centre lies over the blocks it rests on (between the leftmost left edge and the rightmost right edge of the
blocks of the layer below that it touches, ``margin`` inside them), whatever those blocks carry and however the tower below them
balances. Among the safe placements it prefers the one after which the tower's overhang is largest. The rule
is a common naive account of balance (a centre of mass over its own support, not the stack's), and it is not
in the fitted models' space: a cohort of such participants shows whether a fit sees that no model describes it.
"""

from __future__ import annotations

import time

import numpy as np

from overhang_framework.geometry import Block, overhang
from overhang_framework.interfaces import Action, Budget, Decision, Planner, Predictor, Spend, State, Value, World
from overhang_framework.search import ChoiceRule


def locally_supported(state: State, action: Action, width: float, margin: float = 0.0) -> bool:
    """Whether a block of ``width`` placed by ``action`` has its centre over the blocks directly under it, at
    least ``margin`` metres inside their outer edges."""
    if action.layer == 0:
        return True
    under = [b for b in state.geometry.blocks if b.layer == action.layer - 1
             and min(b.right, action.x + width / 2) - max(b.left, action.x - width / 2) > 1e-9]
    if not under:
        return False
    return min(b.left for b in under) + margin - 1e-9 <= action.x <= max(b.right for b in under) - margin + 1e-9


class EdgePlanner(Planner):
    """Scores each legal action by the overhang after it when the placed block is locally supported
    (:func:`locally_supported`, ``margin`` metres inside its support), else 0, and chooses by ``choice`` (``argmax``, ties at random, or ``softmax``
    with inverse temperature ``beta`` per metre). The predictor and the value are not used: no predictor call
    is spent."""

    predictor_free = True

    def __init__(self, world: World, choice: str = "argmax", beta: float = 10.0, margin: float = 0.1):
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 <= margin < 0.3:
            raise ValueError(f"margin must be a number of metres from 0 to below 0.3 (half the narrowest block), "
                             f"got {margin!r}")
        self.world = world
        self.rule = ChoiceRule(choice, beta)
        self.margin = float(margin)

    def scores(self, state: State) -> tuple[list[Action], np.ndarray]:
        """The legal actions of ``state`` and their scores."""
        actions = self.world.legal_actions(state)
        width = state.next_width
        out = np.zeros(len(actions))
        for i, a in enumerate(actions):
            if locally_supported(state, a, width, self.margin):
                out[i] = overhang(state.geometry.add(Block(width, a.x, a.layer)))
        return actions, out

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        actions, scores = self.scores(state)
        if not actions:
            raise RuntimeError("no legal action in this state")
        choice = self.rule.choose(scores, rng)
        spend = Spend(actions_scored=len(actions), seconds=time.perf_counter() - start, depth_completed=1)
        return Decision(actions[choice.index], 1.0 if scores[choice.index] > 0 else 0.0, spend,
                        choice.probability, choice.rank)
