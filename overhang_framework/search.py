"""Search machinery shared by planners: batched expansion, bounds, budgets and choice rules.

A third-party planner builds on these rather than copying them:

* :class:`Expander` scores all the children of a state with one batched
  predictor call, memoised per decision, charged to the decision's
  :class:`~overhang_framework.interfaces.Budget`. The predictor is asked about
  the state's canonical form, with random draws from :func:`node_rng`, a
  generator derived from the decision's seed and the state itself, so a
  search's numbers do not depend on the order in which it visits states or
  on what it prunes.
* :func:`reach_bound` bounds the overhang reachable from a state in a number
  of placements, from geometry alone; values use it for their
  :meth:`~overhang_framework.interfaces.Value.bound`.
* :func:`lookahead_value` is the depth-limited max-product search of the
  paper's lookahead, ``max_pi prod_k p(s_k, a_k) * V(s_{t+D})``, with
  branch-and-bound pruning that never changes its value.
* :class:`ChoiceRule` turns the scores of the root actions into a choice:
  ``argmax`` (ties broken uniformly with the episode's generator) or
  ``softmax`` with an inverse temperature; both report the chosen action's
  probability and rank.
* :func:`risk_weight` makes a search risk-averse (an :class:`Expander`'s ``risk``): each placement's
  chance of standing is replaced by a weight that makes a collapse count more than its expected loss.
"""

from __future__ import annotations

import hashlib
from collections import abc
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import GRID_HALF_WIDTH, Geometry, overhang
from overhang_framework.interfaces import Budget, Predictor, Spend, State, Value, World

#: Relative tolerance under which two scores count as tied (and a bound as not below a score).
TIE = 1e-12


#: How a risk-averse search weighs a placement's chance of standing (:func:`risk_weight`).
RISK_FORMS = ("power", "cvar")


def risk_weight(p, risk: float, form: str = "power") -> np.ndarray:
    """The weight a search of risk aversion ``risk`` (0 to below 1) gives a placement that stands with
    probability ``p``, in place of ``p`` itself in the paper's ``prod_k p(s_k, a_k) * V(s_{t+D})``.

    ``power`` (the default): ``w(p) = p ** (1 / (1 - risk))``, Prelec's (1998) probability weighting of
    elevation ``1 / (1 - risk)`` and curvature 1: at ``risk = 0.5`` a placement counts as if it had to stand
    twice, at 0.75 four times. The product over a plan is the plan's chance of standing raised to the same
    power, so the rule is time-consistent, and every placement keeps its order by ``p``.

    ``cvar``: ``w(p) = max(0, (p - risk) / (1 - risk))``, the conditional value at risk at level
    ``alpha = 1 - risk`` of the placement's two outcomes (collapse: 0; standing: the value of what follows),
    so the product is the nested CVaR of the reward (Ruszczynski 2010; Gagne & Dayan 2022 for human
    planning). Every placement judged to stand with probability at most ``risk`` is worth nothing, so
    where no placement is surer than that the choice among them is at random: a very averse planner with
    no safe option acts as carelessly as it can.

    Both give ``w(p) = p`` at ``risk = 0`` (exactly: the array is returned as it is), ``w(0) = 0``,
    ``w(1) = 1``, ``w(p) <= p`` and less weight for more risk, so a collapse weighs more than its
    expected loss, 0/1 verdicts and every bound stay as they were, and unknown answers (NaN) stay unknown.
    """
    p = np.asarray(p, dtype=float)
    if risk == 0:
        return p
    if form == "cvar":
        return np.maximum(0.0, (p - risk) / (1.0 - risk))
    return np.power(p, 1.0 / (1.0 - risk))


def check_risk(risk, form: str = "power") -> float:
    """``risk`` as a float; :class:`ValueError` unless it is a number from 0 (risk-neutral) to below 1 and
    ``form`` one of :data:`RISK_FORMS`."""
    if isinstance(risk, bool) or not isinstance(risk, (int, float)) or not 0 <= risk < 1:
        raise ValueError(f"risk must be a number from 0 (risk-neutral) to below 1, got {risk!r}")
    if form not in RISK_FORMS:
        raise ValueError(f"unknown risk_form {form!r}; allowed: {', '.join(RISK_FORMS)}")
    return float(risk)


class BudgetExhausted(Exception):
    """The decision's budget ran out before a new predictor call."""


def state_key(state: State) -> tuple:
    """Canonical key of a decision state: the order-independent geometry and the widths still to place."""
    return state.geometry.key, tuple(round(w, 6) for w in state.remaining)


def canonical_state(state: State) -> State:
    """``state`` with its blocks in canonical order (by layer, then x, then width).

    A predictor may treat blocks in order (the IPE draws noise per block);
    asking it about the canonical state makes its answer a function of the
    tower, not of the order in which the search happened to build it.
    """
    blocks = tuple(sorted(state.geometry.blocks, key=lambda b: (b.layer, b.x, b.width)))
    return State(Geometry(blocks), state.remaining)


def mirrored_key(key: tuple) -> tuple:
    """The canonical geometry key of the mirror image (x -> -x) of the geometry with ``key``."""
    return tuple(sorted((w, -x + 0.0, layer) for w, x, layer in key))


def is_symmetric(state: State) -> bool:
    """Whether the state's tower is its own mirror image in x."""
    key = state.geometry.key
    return key == mirrored_key(key)


def node_rng(seed: int, key: tuple) -> np.random.Generator:
    """The generator a predictor uses for the children of the state with ``key``, within one decision."""
    digest = hashlib.blake2b(repr(key).encode(), digest_size=16).digest()
    words = np.frombuffer(digest, dtype=np.uint32).tolist()
    return np.random.default_rng(np.random.SeedSequence([int(seed) & (2**63 - 1), *words]))


class Expansion:
    """The scored children of one state: legal actions, successor states, stability, overhang.

    A predictor that can tell which of its answers are cheap (the world's verdicts, where the static
    stages are sure) may leave the others unknown (NaN) with a ``settle`` function that computes them
    for given children (the full-window reference). :attr:`p` settles every unknown child first, so
    code that reads it sees a complete array; a search reads :attr:`upper` (unknown children counted
    as standing) and settles only the children whose answer could still change its result
    (:func:`settled_scores`, :func:`lookahead_value`), which keeps the result exact.
    """

    def __init__(self, actions: list, children: list, p, overhang: np.ndarray, settle=None, classify=None,
                 risk: float = 0.0, risk_form: str = "power"):
        self.actions, self.children, self.overhang = actions, children, overhang
        self.risk, self.risk_form = risk, risk_form
        # the predictor's answers; with ``risk`` the search reads their weights (:func:`risk_weight`)
        self._stability = np.asarray(p, dtype=float)
        self._p = risk_weight(self._stability, risk, risk_form) if risk else self._stability
        self._settle = settle
        self._classify = classify
        # with ``classify`` every answer starts unknown; :meth:`look` takes the cheap first look (1, 0, or
        # still unknown) for the children a search may need, and :meth:`settle` the dear one
        self._looked = np.zeros(len(self._p), dtype=bool) if classify is not None else np.ones(len(self._p), bool)
        self.settled = 0  # children whose answer was settled on demand

    @property
    def p(self) -> np.ndarray:
        """The probability of standing of every child (unknown ones settled first)."""
        self.settle(np.flatnonzero(np.isnan(self._p)))
        return self._p

    @property
    def unknown(self) -> np.ndarray:
        """Which children's answers are not known yet."""
        return np.isnan(self._p)

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds of :attr:`p`: the known answers, 1 for unknown ones."""
        return np.where(np.isnan(self._p), 1.0, self._p)

    def look(self, indices) -> None:
        """The cheap first look at the children ``indices`` not looked at yet, in one call."""
        todo = [int(i) for i in indices if not self._looked[int(i)]]
        if todo:
            stage = np.asarray(self._classify(todo))
            known = stage >= 0
            self._store(np.asarray(todo)[known], stage[known].astype(float))
            self._looked[todo] = True

    def settle(self, indices) -> None:
        """Compute the answers of the children ``indices`` that are not known yet, in one call."""
        self.look(indices)
        todo = [int(i) for i in indices if np.isnan(self._p[int(i)])]
        if todo:
            self._store(todo, np.asarray(self._settle(todo), dtype=float))
            self.settled += len(todo)

    def _store(self, where, answers: np.ndarray) -> None:
        """Keep the predictor's ``answers`` for the children ``where``, and their weights for the search."""
        if self._stability is not self._p:
            self._stability[where] = answers
        self._p[where] = risk_weight(answers, self.risk, self.risk_form)

    def is_known(self, i: int) -> bool:
        """Whether child ``i``'s answer is known (looked at and sure, or settled)."""
        return not np.isnan(self._p[i])

    def awaits_settling(self, i: int) -> bool:
        """Whether child ``i`` was looked at and is still unknown: only the dear answer will tell."""
        return bool(np.isnan(self._p[i]) and self._looked[i])

    def p_at(self, i: int) -> float:
        """The probability of child ``i`` (settled first when unknown); with ``risk``, its weight."""
        self.settle([i])
        return float(self._p[i])

    def stability_at(self, i: int) -> float:
        """The predictor's probability that child ``i`` stands (settled first when unknown), whatever the
        search's ``risk``: what a decision reports as its predicted stability."""
        self.settle([i])
        return float(self._stability[i])


@dataclass
class SearchStats:
    predictor_calls: int = 0
    actions_scored: int = 0
    nodes_expanded: int = 0
    cache_hits: int = 0
    leaves_pruned: int = 0

    def spend(self, seconds: float, budget: Budget, **extra) -> Spend:
        return Spend(predictor_calls=self.predictor_calls, actions_scored=self.actions_scored,
                     nodes_expanded=self.nodes_expanded, seconds=seconds,
                     budget_exhausted=budget.exhausted(), leaves_pruned=self.leaves_pruned, **extra)


@dataclass
class Expander:
    """Expands states for one decision: legal actions, one batched prediction, memoised by state.

    ``seed`` fixes the predictor's draws for every state of the decision (see
    :func:`node_rng`); draw it from the episode's generator once per decision.
    Before each new predictor call the budget is checked; when it is spent,
    :class:`BudgetExhausted` is raised, unless ``force`` (a planner must be
    able to score the root's children to answer at all). With ``mirror``, a
    state that is its own mirror image in x gets only its actions with
    ``x >= 0``: the others lead to the mirror images of those towers, which
    stand or fall alike when the physics is mirror-symmetric.
    """

    world: World
    predictor: Predictor
    budget: Budget
    seed: int
    resolution: Optional[float] = None
    mirror: bool = False
    lazy: bool = True
    #: Whether a predictor whose lazy answers are ``auto`` (:attr:`lazy_auto`) answers lazily here: in a
    #: planner's search without a budget (the default); a score table sets it false.
    auto_lazy: bool = True
    #: Risk aversion: the search reads each answer's weight (:func:`risk_weight`); 0 is risk-neutral.
    risk: float = 0.0
    risk_form: str = "power"
    stats: SearchStats = field(default_factory=SearchStats)
    _memo: dict = field(default_factory=dict, repr=False)

    def expand(self, state: State, force: bool = False) -> Expansion:
        key = state_key(state)
        hit = self._memo.get(key)
        if hit is not None:
            self.stats.cache_hits += 1
            return hit
        if not force and self.budget.exhausted():
            raise BudgetExhausted
        actions = self.world.legal_actions(state, self.resolution)
        if self.mirror and is_symmetric(state):
            actions = [a for a in actions if a.x >= 0]
        settle = classify = None
        if actions:
            lazy = getattr(self.predictor, "predict_lazy", None) if self.asks_lazily else None
            if lazy is not None:
                p, settle, classify = lazy(canonical_state(state), actions, node_rng(self.seed, key))
            else:
                p = self.predictor.predict(canonical_state(state), actions, node_rng(self.seed, key))
            p = np.asarray(p, dtype=float)
            self.budget.charge(1)
            self.stats.predictor_calls += 1
        else:
            p = np.zeros(0)
        expansion = self._expansion(state, actions, p, settle, classify)
        self._memo[key] = expansion
        return expansion

    @property
    def asks_lazily(self) -> bool:
        """Whether this search takes the predictor's lazy answers where it has them. A predictor whose
        laziness is ``auto`` (``lazy_auto``) is asked lazily only without a budget, where the scores and
        the choice are the same and nothing is charged, and where :attr:`auto_lazy` allows it."""
        if not self.lazy:
            return False
        if getattr(self.predictor, "lazy_auto", False):
            return self.auto_lazy and not self.budget.limited
        return True

    @property
    def settle_batch(self) -> int:
        """How many unknown children a search settles together: the world's physics workers, or more where
        the predictor asks for it (a network's forward pass costs less per tower in a batch)."""
        return max(1, int(getattr(self.world, "workers", 1) or 1), int(getattr(self.predictor, "settle_batch", 1) or 1))


    @property
    def settle_inner(self) -> bool:
        """Whether a search settles the children of an inner node together, before ordering them (a
        predictor whose answers cost about the same in any batch, as a network's or the IPE's, says so with
        ``settle_inner``): their known answers order and prune the search as well as eager answers would,
        and only the leaves' answers are left to settle as needed."""
        return bool(getattr(self.predictor, "settle_inner", False))

    @property
    def dear_answers(self) -> bool:
        """Whether the answers this search leaves unknown are dear to settle, so that a search defers settling
        them (:func:`root_scores`' ``defer``): the predictor answers lazily here and settles one child at a time
        rather than an inner node's children together (``settle_inner`` false). That is the veridical
        predictor with the world's own verdicts, where a tower the static stages leave unsure needs the
        full-window reference run; a network's or the IPE's answers cost about the same in any batch."""
        return self.asks_lazily and getattr(self.predictor, "predict_lazy", None) is not None \
            and not self.settle_inner

    def expand_many(self, states: Sequence[State]) -> None:
        """Expand every state of ``states`` not expanded yet, with one :meth:`Predictor.predict_many` call.

        Each state counts as one predictor call against the budget, as if
        expanded alone; a budget that cannot pay for all of them expands none
        (the search then expands them one by one until it runs out).
        """
        lazy = getattr(self.predictor, "predict_lazy", None) is not None and self.asks_lazily
        lazy_for = getattr(self.predictor, "lazy_for", None)
        todo, seen = [], set()
        for state in states:
            key = state_key(state)
            if key not in self._memo and key not in seen and not state.done \
                    and not (lazy and (lazy_for is None or lazy_for(state))):
                seen.add(key)
                todo.append((key, state))
        if len(todo) < 2:
            return
        if self.budget.predictor_calls is not None and \
                self.budget.calls_used + len(todo) > self.budget.predictor_calls:
            return
        if self.budget.exhausted():
            return
        parts = []
        for key, state in todo:
            actions = self.world.legal_actions(state, self.resolution)
            if self.mirror and is_symmetric(state):
                actions = [a for a in actions if a.x >= 0]
            parts.append((key, state, actions))
        asked = [(canonical_state(state), actions) for _, state, actions in parts if actions]
        rngs = [node_rng(self.seed, key) for key, _, actions in parts if actions]
        answers = iter(self.predictor.predict_many(asked, rngs)) if asked else iter(())
        for key, state, actions in parts:
            p = np.asarray(next(answers), dtype=float) if actions else np.zeros(0)
            if actions:
                self.budget.charge(1)
                self.stats.predictor_calls += 1
            self._memo[key] = self._expansion(state, actions, p)

    def _expansion(self, state: State, actions: list, p: np.ndarray, settle=None, classify=None) -> Expansion:
        children = Successors(self.world, state, actions)
        base = overhang(state.geometry)
        width = state.next_width or 0.0
        reach = np.array([abs(a.x) + width / 2 for a in actions], dtype=float)
        self.stats.actions_scored += len(actions)
        self.stats.nodes_expanded += 1
        return Expansion(actions, children, p, np.maximum(base, reach) if len(reach) else reach, settle, classify,
                         self.risk, self.risk_form)


class Successors(abc.Sequence):
    """The successor states of a state's actions, each made when first asked for: a search reaches few of
    a leaf's children as states (their values come from the overhang, their answers from the predictor),
    and making them all was a tenth of a deep search's time."""

    __slots__ = ("world", "state", "actions", "_made")

    def __init__(self, world: World, state: State, actions: Sequence):
        self.world, self.state, self.actions = world, state, actions
        self._made: list = [None] * len(actions)

    def __len__(self) -> int:
        return len(self.actions)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        child = self._made[i]
        if child is None:
            child = self._made[i] = self.world.successor(self.state, self.actions[i])
        return child


def max_reach(world: World, state: State, resolution: Optional[float] = None) -> float:
    """The largest overhang one more legal placement can give (the state's own if none is legal)."""
    base = overhang(state.geometry)
    if state.done:
        return base
    width = state.next_width
    arrays = getattr(world, "legal_xs", None)  # a world may give its placements as arrays, without objects
    if arrays is not None:
        xs, _ = arrays(state, resolution)
        return max(base, float(np.abs(xs).max()) + width / 2) if len(xs) else base
    actions = world.legal_actions(state, resolution)
    return max([base] + [abs(a.x) + width / 2 for a in actions])


def reach_bound(world: World, state: State, depth: int, resolution: Optional[float] = None,
                step: float = 0.0) -> float:
    """An upper bound on the overhang of any geometry reachable from ``state`` in ``depth`` placements.

    Geometry alone: the next block's reach is computed exactly over its legal
    placements, and each later block rests on some block below with a positive
    overlap, so it extends the tower by less than its width. Capped by the grid.
    With ``step``, the lattice every centre distance and half width lies on
    (:func:`score_step`), a positive overlap is at least one step, so each later
    block extends the tower by at most its width less one step.
    """
    depth = min(depth, len(state.remaining))
    if depth <= 0:
        return overhang(state.geometry)
    bound = max_reach(world, state, resolution) + sum(state.remaining[1:depth]) - step * (depth - 1)
    return max(overhang(state.geometry), min(bound, GRID_HALF_WIDTH))


def _leaf_values(value: Value, expansion: Expansion) -> np.ndarray:
    fast = getattr(value, "children_values", None)
    if fast is not None:
        return np.asarray(fast(expansion), dtype=float)
    return np.array([value(child) for child in expansion.children], dtype=float)


def _below(bound: Optional[float], threshold: float) -> bool:
    """Whether ``bound`` proves a score under ``threshold`` (ties are never pruned)."""
    return bound is not None and threshold > 0 and bound < threshold * (1 - TIE) - 1e-15


def settled_scores(expansion: Expansion, values: np.ndarray, floor: float = 0.0, exact_all: bool = False,
                   batch: int = 1, step: float = 0.0) -> np.ndarray:
    """``p * values`` for every child, settling unknown answers only where they can matter.

    Exact for every child scoring at least ``floor`` and at least every other child's score (ties
    included); another child may get an upper bound of its score instead (still below the best, or
    below ``floor``). With ``exact_all`` every score is exact. Unknown children are settled best
    bound first, ``batch`` at a time. With ``step`` > 0 the scores are known to lie on a lattice of
    that spacing (see :func:`lookahead_value`): a child is settled only if it could beat the best known
    score by a whole step, so the maximum is still exact but a child tied with it may keep its bound.
    """
    values = np.asarray(values, dtype=float)
    unknown = expansion.unknown
    if exact_all or not unknown.any():
        return expansion.p * values
    upper = expansion.upper * values
    known = ~unknown
    best = float(upper[known].max()) if known.any() else 0.0
    expansion.look([i for i in np.flatnonzero(unknown) if not _below(upper[i], _wanted(best, floor, step))])
    unknown = expansion.unknown
    upper = expansion.upper * values
    scores = upper.copy()
    known = ~unknown
    best = float(scores[known].max()) if known.any() else 0.0
    order = [int(i) for i in np.argsort(-upper, kind="stable") if unknown[i]]
    k = 0
    while k < len(order):
        if _below(upper[order[k]], _wanted(best, floor, step)) or upper[order[k]] <= 0:
            break
        group = [i for i in order[k:k + batch] if not _below(upper[i], _wanted(best, floor, step))]
        expansion.settle(group)
        for i in group:
            scores[i] = expansion.p_at(i) * values[i]
            best = max(best, float(scores[i]))
        k += batch
    return scores


def binary_verdicts(predictor: Predictor) -> bool:
    """Whether every probability ``predictor`` gives is 0 or 1 (one deterministic verdict per tower)."""
    return bool(getattr(predictor, "world_verdicts", False)
                or (getattr(predictor, "deterministic", False) and getattr(predictor, "K", None) == 1))


def lattice_step(world: World, predictor: Predictor, value: Value, state: State) -> float:
    """The spacing of the lattice every search score from ``state`` lies on (:func:`score_step`), when it
    does: 0/1 verdicts (:func:`binary_verdicts`) times a value that is an overhang on the world's grid
    (``value.lattice``); else 0."""
    if not (binary_verdicts(predictor) and getattr(value, "lattice", False)):
        return 0.0
    widths = sorted({b.width for b in state.geometry.blocks} | set(state.remaining))
    return score_step(getattr(world, "resolution", None) or 0.1, widths)


def score_step(resolution: float, widths: Sequence[float]) -> float:
    """The spacing of the lattice that every overhang of a task lies on: placements sit at
    ``k * resolution`` and a block reaches half its width beyond its centre, so every overhang is a
    whole multiple of the greatest common divisor of ``resolution`` and the half widths (0.1 for the
    default grid). Scores of 0/1 verdicts times an overhang lie on the same lattice."""
    from fractions import Fraction
    from math import gcd, lcm

    parts = [Fraction(float(v)).limit_denominator(10**6) for v in (resolution, *(w / 2 for w in widths))]
    den = lcm(*(f.denominator for f in parts))
    return gcd(*(f.numerator * (den // f.denominator) for f in parts)) / den


def _wanted(best: float, floor: float, step: float) -> float:
    """The least score worth looking for: ``floor``, and with ``step`` a whole step above ``best``
    (``best`` itself without one); just under it, so that rounding never hides a score on the lattice."""
    return max(floor, best + step * (1 - 1e-6)) if step > 0 and best > 0 else max(floor, best)


def lookahead_value(expander: Expander, value: Value, state: State, depth: int,
                    threshold: float = 0.0, memo: Optional[dict] = None, beam: Optional[int] = None,
                    prefetch: bool = False, step: float = 0.0, defer: bool = False, settle_by_bound: bool = False,
                    optimistic: bool = False) -> float:
    """``max`` over action sequences of length ``depth`` of ``prod p * V(leaf)`` from ``state``.

    Branch and bound: a child whose score cannot reach ``threshold`` (or the
    best found so far) is skipped, using ``p <= 1`` along the path and the
    value's :meth:`~overhang_framework.interfaces.Value.bound`. The result is
    exact when it is at least ``threshold``; otherwise it is some number below
    ``threshold`` (the true value is below it too). Ties are never pruned. The
    sequence stops early when the episode ends. ``memo`` carries results
    between calls of one decision. ``beam`` keeps only that many children of
    each inner node, the best by ``p * bound`` (an approximation).
    ``prefetch`` expands all the children of a node one level
    above the leaves together (:meth:`Expander.expand_many`), which is faster
    when one large physics call costs much less than many small ones, at the
    cost of scoring children that a bound would have skipped.
    Children whose answer the predictor left unknown (:class:`Expansion`) count as standing in the
    bounds and are settled only when they are about to be searched, so the result is the same.

    ``step`` > 0 says that every score lies on a lattice of that spacing (0/1 verdicts times an
    overhang on the grid, :func:`score_step`): once a score is found, only a whole step more counts,
    so subtrees that could at best tie it are skipped. The value is the same; which of several tied
    sequences reached it first is not searched for. A ``memo`` must not mix calls with different ``step``.

    ``defer`` searches the subtree of an inner child whose answer is still unknown before settling it,
    as if it stood, and settles it only when that subtree could beat the floor: where answers are dear
    (the full-window reference) and most subtrees cannot, most unknown inner children are never
    settled. The value is the same: a child's subtree value does not depend on its own answer.

    ``settle_by_bound`` settles an inner child whose answer is still unknown only when an optimistic value
    of its subtree could beat the floor: the same search with every unknown answer counted as standing and
    none settled (``optimistic``, which takes only the cheap first looks and returns an upper bound of the
    value). Where answers are dear and subtrees are mostly decided by the cheap looks, most unknown children
    whose geometry could reach far are never settled, and nothing is settled for a subtree that cannot win.
    """
    memo = {} if memo is None else memo
    depth = min(depth, len(state.remaining))
    if depth == 0:
        return float(value(state))
    key = (state_key(state), depth, "upper") if optimistic else (state_key(state), depth)
    known = memo.get(key)
    if known is not None:
        result, exact, tried = known
        if exact or threshold >= tried:
            return result
    expansion = expander.expand(state)
    best = 0.0
    if depth == 1 and optimistic:
        values = _leaf_values(value, expansion)
        upper = expansion.upper * values
        expansion.look([i for i in range(len(upper)) if upper[i] > 0 and not _below(upper[i], threshold)])
        best = float((expansion.upper * values).max()) if len(values) else 0.0
    elif depth == 1:
        scores = settled_scores(expansion, _leaf_values(value, expansion), threshold, batch=expander.settle_batch,
                                step=step)
        best = float(scores.max()) if len(scores) else 0.0
    else:
        upper = expansion.upper
        bounds = np.array([_bound(value, child, depth - 1) for child in expansion.children], dtype=float)
        wanted = [i for i in range(len(upper)) if upper[i] > 0 and not _below(upper[i] * bounds[i], threshold)]
        if expander.settle_inner and not optimistic:
            expansion.settle(wanted)
        else:
            expansion.look(wanted)
        upper = expansion.upper
        order = np.argsort(-_products(upper, bounds), kind="stable")[:beam]
        if depth == 2 and prefetch:
            floor = threshold
            expander.expand_many([expansion.children[i] for i in order
                                  if upper[i] > 0 and not _below(upper[i] * bounds[i], floor)])
        for n, i in enumerate(order):
            floor = _wanted(best, threshold, step)
            if upper[i] <= 0 or _below(upper[i] * bounds[i], floor):
                expander.stats.leaves_pruned += 1
                continue
            if optimistic:  # unknown answers count as standing; nothing is settled
                child = lookahead_value(expander, value, expansion.children[i], depth - 1, floor / upper[i], memo,
                                        beam, prefetch, step, optimistic=True)
                best = max(best, float(upper[i] * child))
                continue
            if settle_by_bound and expansion.awaits_settling(i):
                reach = _optimistic(expander, value, expansion.children[i], depth - 1, floor, memo, beam, prefetch,
                                    step)
                if reach <= 0 or _below(reach, floor):
                    continue
            if defer and expansion.awaits_settling(i):
                # its subtree first, as if it stood: settled only if the subtree could beat the floor
                child = lookahead_value(expander, value, expansion.children[i], depth - 1,
                                        floor, memo, beam, prefetch, step, defer)
                if _below(child, floor):
                    continue
                p_i = expansion.p_at(i)
                if p_i <= 0:
                    continue
                if p_i < 1:
                    child = lookahead_value(expander, value, expansion.children[i], depth - 1,
                                            floor / p_i, memo, beam, prefetch, step, defer)
                best = max(best, float(p_i * child))
                continue
            _settle_next(expander, expansion, order, n, upper, bounds, floor)
            p_i = expansion.p_at(i)  # settled just above
            if p_i <= 0:
                continue
            child = lookahead_value(expander, value, expansion.children[i], depth - 1,
                                    floor / p_i, memo, beam, prefetch, step, defer, settle_by_bound)
            best = max(best, float(p_i * child))
    exact = best >= threshold * (1 - TIE) or threshold <= 0
    memo[key] = (best, exact, threshold)
    return best


def _optimistic(expander: Expander, value: Value, child: State, depth: int, floor: float, memo: dict,
                beam: Optional[int], prefetch: bool, step: float) -> float:
    """An upper bound of ``child``'s subtree value, exact for the optimistic search when at least ``floor``:
    every unknown answer counted as standing, none settled (only the cheap first looks)."""
    return lookahead_value(expander, value, child, depth, floor, memo, beam, prefetch, step, optimistic=True)


def _settle_next(expander: Expander, expansion: Expansion, order, n: int, upper, bounds, floor: float) -> None:
    """Settle child ``order[n]`` if unknown, with the next unknown children that the bound does not skip
    at ``floor`` (up to the expander's batch)."""
    i = order[n]
    if expansion.is_known(i):
        return
    group = [i]
    for j in order[n + 1:]:
        if len(group) >= expander.settle_batch:
            break
        if expansion.awaits_settling(j) and upper[j] > 0 \
                and not _below(upper[j] * bounds[j], floor):
            group.append(j)
    expansion.settle(group)


def _products(p: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """``p * bounds``, with 0 where ``p`` is 0 (an unbounded child that cannot stand scores 0)."""
    out = np.zeros(len(p))
    np.multiply(p, bounds, out=out, where=p > 0)
    return out


def _bound(value: Value, state: State, depth: int) -> float:
    bound = value.bound(state, depth)
    return np.inf if bound is None else float(bound)


def root_scores(expander: Expander, value: Value, state: State, depth: int, exact_all: bool,
                first: Optional[int] = None, memo: Optional[dict] = None,
                beam: Optional[int] = None, prefetch: bool = False, defer: bool = False,
                step: float = 0.0) -> np.ndarray:
    """The score ``p(s, a) * best continuation`` of every root action, at horizon ``depth``.

    With ``exact_all`` every score is exact (what a softmax rule needs);
    otherwise only the best ones are, and the others may be any number below
    the best (enough for argmax, and much cheaper). ``first`` is explored
    first, e.g. the previous iteration's choice, to tighten the bound early.
    ``beam`` and ``prefetch`` are passed on to :func:`lookahead_value`
    (the root's own children are expanded one by one, so that pruning keeps its
    effect where the subtrees are largest).

    ``defer`` searches, at the root and below (:func:`lookahead_value`), the subtree of a child whose
    answer only the dear settling can give (:meth:`Expansion.awaits_settling`: the reference's full-window
    run) before settling it, as if it stood, and settles it only when that subtree could still beat the
    best score (every score, with ``exact_all``, unless the subtree is worth 0). The scores that matter are
    the same, ties included: a child's subtree value does not depend on its own answer, and a score is only
    skipped when even a standing child could not reach the best. It pays where settling is dear
    (:attr:`Expander.dear_answers`); elsewhere the optimistic searches only add work.

    ``step`` is passed on to the subtrees (:func:`lookahead_value`): their values stay exact, so the root
    scores, their ties and the choice are the same. The root's own children are never compared on it.
    """
    memo = {} if memo is None else memo
    expansion = expander.expand(state, force=True)
    n = len(expansion.actions)
    scores = np.zeros(n)
    if depth <= 1 or len(state.remaining) <= 1:
        return settled_scores(expansion, _leaf_values(value, expansion), exact_all=exact_all,
                              batch=expander.settle_batch)
    if expander.settle_inner or exact_all:
        expansion.p  # every root score must be exact, or the predictor settles a node's children at once
    expansion.look(range(n))
    upper = expansion.upper
    bounds = np.array([_bound(value, child, depth - 1) for child in expansion.children], dtype=float)
    order = list(np.argsort(-_products(upper, bounds), kind="stable"))
    if first is not None and first in order:
        order.remove(first)
        order.insert(0, first)
    best = 0.0
    for k, i in enumerate(order):
        if upper[i] <= 0:
            expander.stats.leaves_pruned += 1
            continue
        floor = 0.0 if exact_all else best
        if _below(upper[i] * bounds[i], floor):
            expander.stats.leaves_pruned += 1
            scores[i] = upper[i] * bounds[i]
            continue
        if defer and expansion.awaits_settling(i):  # (every root answer is settled when all scores must be exact)
            reach = _optimistic(expander, value, expansion.children[i], depth - 1, floor, memo, beam, prefetch, step)
            if reach <= 0 or _below(reach, floor):
                expander.stats.leaves_pruned += 1
                scores[i] = max(reach, 0.0)  # a bound of its score, below the best
                continue
        _settle_next(expander, expansion, order, k, upper, bounds, floor)
        p_i = expansion.p_at(i)  # settled just above
        if p_i <= 0:
            continue
        scores[i] = p_i * lookahead_value(expander, value, expansion.children[i], depth - 1,
                                          floor / p_i, memo, beam, prefetch, step, settle_by_bound=defer)
        best = max(best, scores[i])
    return scores


@dataclass(frozen=True)
class Choice:
    index: int
    probability: float
    rank: int


class ChoiceRule:
    """How a planner turns the scores of its root actions into one action.

    ``argmax`` picks a best-scoring action, uniformly among ties;
    ``softmax`` samples with probabilities proportional to
    ``exp(beta * score)`` (``beta``, the inverse temperature, in 1/metres of
    overhang). Sampling uses the episode's generator, so a seed fixes the
    choice. The rank of an action is 1 plus the number of actions scoring
    strictly more.
    """

    RULES = ("argmax", "softmax")

    def __init__(self, rule: str = "argmax", beta: float = 10.0):
        if rule not in self.RULES:
            raise ValueError(f"unknown choice rule {rule!r}; allowed: {', '.join(self.RULES)}")
        if isinstance(beta, bool) or not isinstance(beta, (int, float)) or not np.isfinite(beta) or beta < 0:
            raise ValueError(f"beta must be a number >= 0, got {beta!r}")
        self.rule, self.beta = rule, float(beta)

    @property
    def needs_all_scores(self) -> bool:
        return self.rule == "softmax"

    def probabilities(self, scores: Sequence[float]) -> np.ndarray:
        s = np.asarray(scores, dtype=float)
        if s.size == 0:
            return s
        if self.rule == "argmax":
            best = ties(s)
            out = np.zeros(s.size)
            out[best] = 1.0 / len(best)
            return out
        z = self.beta * (s - s.max())
        w = np.exp(z)
        return w / w.sum()

    def choose(self, scores: Sequence[float], rng: np.random.Generator) -> Choice:
        s = np.asarray(scores, dtype=float)
        if s.size == 0:
            raise ValueError("no action to choose from")
        probs = self.probabilities(s)
        if self.rule == "argmax":
            best = ties(s)
            i = int(best[rng.integers(len(best))]) if len(best) > 1 else int(best[0])
        else:
            i = int(rng.choice(s.size, p=probs))
        rank = 1 + int(np.sum(s > s[i] * (1 + TIE) + 1e-15))
        return Choice(i, float(probs[i]), rank)


def ties(scores: np.ndarray) -> np.ndarray:
    """Indices of the scores tied with the maximum."""
    top = scores.max()
    return np.flatnonzero(scores >= top - max(abs(top) * TIE, 1e-12))
