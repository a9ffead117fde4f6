"""Depth-D lookahead: the paper's ``U(pi | s_t) = prod_k p(s_k, a_k) * V(s_{t+D})``, searched exactly."""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from overhang_framework.interfaces import Budget, Decision, Planner, Predictor, State, Value, World
from overhang_framework.search import BudgetExhausted, ChoiceRule, Expander, check_risk, lattice_step, root_scores


class LookaheadPlanner(Planner):
    """Plays the first action of the best action sequence of length ``depth``.

    Every legal action sequence over the world's discretised action set is
    considered (fewer steps when the episode ends sooner); every child of a
    state is scored in one batched predictor call, and verdicts are shared
    through the world's physics cache. Branch and bound (``p <= 1`` along a
    path, the value's bound on what a subtree can reach) skips subtrees that
    cannot change the choice; ``prune=false`` searches everything, for checking.
    ``beam`` keeps only that many children per inner node (an approximation;
    ``null``: exhaustive).

    With a budget (``condition=time_limited``) the search deepens
    iteratively, depth 1, 2, ..., and plays the best action of the deepest
    depth it completed when the budget runs out. ``choice`` is ``argmax`` or
    ``softmax`` over the root actions' scores with inverse temperature ``beta``.

    ``defer`` (without a budget, where settling is dear:
    :attr:`~overhang_framework.search.Expander.dear_answers`, the veridical predictor with the world's
    verdicts): a child whose answer only the full-window reference can give has its subtree searched
    first, optimistically (unsure towers counted as standing, none simulated), and is simulated only if
    that subtree could still change the choice (:func:`~overhang_framework.search.root_scores`); the
    scores, the tied best actions and the choice are the same. Under a budget the search settles as
    before, since deferring changes which calls are charged; other predictors settle as before too.

    ``risk`` (0 to below 1; 0, the paper's, is risk-neutral) makes the search risk-averse: every ``p`` of
    the product is replaced by its weight (:func:`~overhang_framework.search.risk_weight`): with
    ``risk_form=power`` ``p ** (1 / (1 - risk))``, with ``cvar`` the nested conditional value at risk
    ``max(0, (p - risk) / (1 - risk))``; a collapse then weighs more than its expected loss.
    """

    def __init__(self, world: World, depth: int = 2, beam: Optional[int] = None, prune: bool = True,
                 choice: str = "argmax", beta: float = 10.0, defer: bool = True, risk: float = 0.0,
                 risk_form: str = "power"):
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            raise ValueError(f"depth must be a whole number >= 1, got {depth!r}")
        if beam is not None and (isinstance(beam, bool) or not isinstance(beam, int) or beam < 1):
            raise ValueError(f"beam must be a whole number >= 1 or null, got {beam!r}")
        if not isinstance(prune, bool):
            raise ValueError(f"prune must be true or false, got {prune!r}")
        if not isinstance(defer, bool):
            raise ValueError(f"defer must be true or false, got {defer!r}")
        self.defer = defer
        self.risk = check_risk(risk, risk_form)
        self.risk_form = risk_form
        self.world = world
        self.depth = depth
        self.beam = beam
        self.prune = prune
        self.rule = ChoiceRule(choice, beta)

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        expander = Expander(self.world, predictor, budget, seed=int(rng.integers(2**63)), risk=self.risk,
                            risk_form=self.risk_form)
        horizon = max(1, min(self.depth, len(state.remaining)))
        depths = range(1, horizon + 1) if budget.limited else [horizon]
        leaf_value = value if self.prune else _Unbounded(value)
        scores, completed, first, memo = None, 0, None, {}
        prefetch = self.prefetches(predictor, budget)
        defer = self.defer and not budget.limited and expander.dear_answers
        # with deferred settling and argmax, subtrees compare scores on their lattice (0/1 verdicts times
        # overhangs): their values are exact, and what only ties a found score is not settled for. (A value
        # reached along another of several tied sequences may differ in its last bit, which argmax's ties
        # absorb; softmax keeps its scores to the bit.)
        exact_all = self.rule.needs_all_scores
        step = lattice_step(self.world, predictor, value, state) if defer and self.prune and not exact_all else 0.0
        for depth in depths:
            try:
                found = root_scores(expander, leaf_value, state, depth, self.rule.needs_all_scores,
                                    first=first, memo=memo, beam=self.beam, prefetch=prefetch,
                                    defer=defer, step=step)
            except BudgetExhausted:
                break
            scores, completed = found, depth
            first = int(np.argmax(found))
        actions = expander.expand(state, force=True)
        if not actions.actions:
            raise RuntimeError("no legal action in this state")
        choice = self.rule.choose(scores, rng)
        spend = expander.stats.spend(time.perf_counter() - start, budget, depth_completed=completed)
        return Decision(actions.actions[choice.index], actions.stability_at(choice.index), spend,
                        choice.probability, choice.rank)

    def prefetches(self, predictor: Predictor, budget: Budget) -> bool:
        """Whether the search expands the children of a node one level above the leaves together.

        That pays for physics, where one large call costs much less than many small ones. A network
        (a ``batched`` predictor) costs about the same per tower in any batch, and from depth 3 the
        towers the bounds would skip outnumber the rest, so its searches expand each node as they reach
        it, unless a budget counts the calls (the calls charged decide how deep a budgeted search gets,
        and they stay as they were) or the network's answers depend on the batch (``batch_invariant``
        false: torch), so that the scores are the same either way, to the bit.
        """
        network = getattr(predictor, "batched", False) and getattr(predictor, "batch_invariant", False)
        return budget.limited or self.depth < 3 or not network


class _Unbounded(Value):
    """A value with its bound hidden, so that a search prunes nothing."""

    def __init__(self, value: Value):
        self.value = value
        self.children_values = getattr(value, "children_values", None)

    def __call__(self, state: State) -> float:
        return self.value(state)
