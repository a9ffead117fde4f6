"""A simulated participant's choice as one object: ``sample`` (what the simulator does) and ``prob`` (the
likelihood a fit uses), on a bank of the IPE's noise draws that both share.

A participant with the IPE of ``K`` simulations draws fresh noise at every decision: each node of its search
asks ``K`` perturbed simulations of every child, under draws the node's children share (common random numbers
within a call, :mod:`overhang_builtins.simulation`). The probability that it chooses action ``a`` in state
``s`` is therefore an average over its own prediction noise::

    P(a | s) = (1 - lapse) * E_noise[ E_percept[ softmax_beta(S(seen, noise)) mapped to s ] ]_a + lapse / n

where ``S`` are the planner's exact root scores (depth ``D``, risk weight ``w``, the hand's average over the
motor noise it plans for) and ``n`` the number of legal actions. A likelihood that scores each state with
one fixed draw of the noise (the fit's score tables) leaves the participant's own sampling noise out.

**The bank.** A :class:`VerdictBank` holds, for every node it is asked about, ``size`` (``B``) noise draws of
its own (seeded by the bank's seed and the node's canonical key) and the verdict of any tower after the node
under each. An IPE of ``K`` simulations whose noise is the bank's draws (:class:`BankIPE`) draws, at each
call, ``K`` of the node's ``B`` draws with replacement: that is the IPE with its noise drawn from the bank's
empirical distribution, which stands for the true one (200 draws estimate a probability of standing to
about ±0.035 at worst). The simulator (:meth:`BankChoice.sample`, the participants' own
:func:`~overhang_framework.behaviour.participants.decide`) and the likelihood (:meth:`BankChoice.prob`) see
the same bank, so they agree exactly when ``prob`` is right, and the bank makes both affordable.

**The likelihood.** ``prob`` marginalises the participant's noise by Monte Carlo, Rao-Blackwellised over
the softmax: for each of ``draws`` samples it draws every node's ``K`` bank columns (and, with a percept,
the tower seen), computes the root scores of the whole search tree array-wise, and averages the softmax
probabilities. The estimate of each ``P(a)`` is unbiased; its Monte Carlo standard error is reported by
:meth:`BankChoice.prob_error`. With ``K = 1`` at depth 1 and no percept it is exact: the average over the
bank's ``B`` columns.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np

from overhang_framework.geometry import Action, overhang
from overhang_framework.interfaces import Predictor, State, World
from overhang_framework.search import node_rng, risk_weight, state_key

#: Noise draws a bank holds per node (the issue of fairness: at least 200).
BANK_SIZE = 200
#: Monte Carlo samples of the participant's noise behind each ``prob``.
DRAWS = 20_000
#: Verdict rows a bank keeps (about 300 bytes each): past them it forgets its least recently asked nodes, whose
#: rows are the same numbers when asked again (a percept's towers are seldom seen twice).
MAX_ROWS = 2_000_000
#: Elements of one gathered array of a Monte Carlo chunk (bounds the memory ``prob`` uses).
CHUNK_ELEMENTS = 20_000_000


class VerdictBank:
    """``size`` noise draws of the IPE at noise ``sigma`` per node, and the verdicts of towers under them.

    ``verdicts(state, actions)`` is a boolean ``(len(actions), size)`` array: the verdict of the tower after each
    action under each of the node's draws. A verdict depends on the node, the action and the draw only (the IPE
    draws a call's noise once for every candidate, and the static backend decides each scene alone), so the bank
    computes each action's row once, when first asked, and keeps it (up to ``max_rows`` rows: then the least
    recently asked nodes are forgotten, and made again, the same, if asked again).
    """

    def __init__(self, world: World, sigma: float = 0.03, size: int = BANK_SIZE, seed: int = 0,
                 predictor: Optional[dict] = None, max_rows: int = MAX_ROWS):
        from overhang_framework.plugins import Registry

        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"a verdict bank's size must be a whole number >= 1, got {size!r}")
        self.world, self.size, self.seed, self.sigma = world, int(size), int(seed), float(sigma)
        config = {"name": "ipe", **dict(predictor or {}), "K": self.size, "sigma": self.sigma}
        self.ipe = Registry().create("predictor", config, world=world)
        self._rows: OrderedDict[tuple, dict[tuple, np.ndarray]] = OrderedDict()
        self._held = 0
        self.max_rows = int(max_rows)
        self.computed = 0

    def verdicts(self, state: State, actions: Sequence[Action]) -> np.ndarray:
        key = state_key(state)
        rows = self._rows.get(key)
        if rows is None:
            rows = self._rows[key] = {}
        else:
            self._rows.move_to_end(key)
        missing = [a for a in actions if (a.x, a.layer) not in rows]
        if missing:
            found = self.ipe.sample_verdicts(state, missing, node_rng(self.seed, key))
            for a, row in zip(missing, found):
                rows[(a.x, a.layer)] = row
            self.computed += len(missing) * self.size
            self._held += len(missing)
            while self._held > self.max_rows and len(self._rows) > 1:  # the oldest nodes: made again if asked
                _, dropped = self._rows.popitem(last=False)
                self._held -= len(dropped)
        if not len(actions):
            return np.zeros((0, self.size), dtype=bool)
        return np.stack([rows[(a.x, a.layer)] for a in actions])


class BankIPE(Predictor):
    """The IPE of ``K`` simulations whose noise comes from ``bank``: each call draws ``K`` of the node's bank
    draws with replacement, shared by the call's candidates, and answers the fraction that stand."""

    deterministic = False

    def __init__(self, bank: VerdictBank, K: int):
        if isinstance(K, bool) or not isinstance(K, int) or K < 1:
            raise ValueError(f"K must be a whole number >= 1, got {K!r}")
        self.bank, self.K = bank, int(K)

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        if not actions:
            return np.zeros(0)
        columns = rng.integers(self.bank.size, size=self.K)
        return self.bank.verdicts(state, actions)[:, columns].mean(axis=1)


@dataclass(frozen=True)
class ChoiceParams:
    """A simulated participant's parameters that shape one choice (``docs/participants.md``): the IPE's ``K`` and
    the search's ``depth``; the softmax's ``beta``; the ``lapse``; the planner's ``risk`` (``risk_form``); the
    motor noise its planner plans for (``hand``, metres; the hand predictor's ``nodes``); its perceptual noise
    (``percept``, metres)."""

    depth: int = 1
    K: int = 10
    beta: float = 10.0
    lapse: float = 0.0
    risk: float = 0.0
    risk_form: str = "power"
    hand: float = 0.0
    hand_nodes: int = 3
    percept: float = 0.0
    switch: int = 0

    def label(self) -> str:
        parts = [f"D{self.depth}", f"K{self.K}", f"beta {self.beta:g}"]
        for name in ("lapse", "risk", "hand", "percept", "switch"):
            if getattr(self, name):
                parts.append(f"{name} {getattr(self, name):g}")
        return ", ".join(parts)


@dataclass
class _Node:
    """One node of a search tree: its children's actions, overhangs, keys and the bank's answers for them."""

    state: State
    actions: list
    overhang: np.ndarray
    answers: np.ndarray  # (children, B): verdicts, or the hand's averages of verdicts
    children: list = field(default_factory=list)  # child keys, for nodes above the leaves


class BankChoice:
    """The choice of a simulated participant with parameters ``params`` whose IPE draws from ``bank``.

    :meth:`sample` is the simulator's decision (:func:`overhang_framework.behaviour.participants.decide`, with
    the lookahead planner and a softmax, no call budget and no motor noise: the grid action chosen);
    :meth:`prob` its probability of each of ``world.legal_actions(state)``.
    """

    def __init__(self, world: World, value: Any, bank: VerdictBank, params: ChoiceParams, draws: int = DRAWS,
                 seed: int = 0, trees: Optional[dict] = None, late: Optional[Predictor] = None):
        self.world, self.value, self.bank, self.params = world, value, bank, params
        self.draws, self.seed = int(draws), int(seed)
        if isinstance(params.switch, bool) or not isinstance(params.switch, int) or params.switch < 0:
            raise ValueError(f"switch must be a whole number of blocks >= 0 (0: no CNN), got {params.switch!r}")
        #: the hybrid's late part (a deterministic predictor, the CNN unless given), built when first needed
        self._late = late
        #: the search trees by (state, horizon): shared by choices of one bank and hand that differ in K, risk or
        #: softmax only (a tree holds the bank's answers, which those do not change)
        self._trees: dict[tuple, dict] = {} if trees is None else trees

    # --- the simulator ----------------------------------------------------------------------------------

    def _agent(self):
        if getattr(self, "_built", None) is None:
            from overhang_builtins.hand import HandPredictor
            from overhang_builtins.lookahead import LookaheadPlanner

            from overhang_framework.behaviour.participants import Cohort, ConditionSpec, Participant, TimeModel

            p = self.params
            predictor: Predictor = BankIPE(self.bank, p.K)
            if p.switch:
                predictor = self.hybrid()
            if p.hand:
                predictor = HandPredictor(self.world, inner=predictor, sd=p.hand, nodes=p.hand_nodes)
            planner = LookaheadPlanner(self.world, depth=p.depth, choice="softmax", beta=p.beta, risk=p.risk,
                                       risk_form=p.risk_form)
            spec = ConditionSpec("unconstrained", 1, None, None)
            cohort = Cohort("choice", (spec,), None, {}, TimeModel(1.0, 0.0, 0.0), 0.0, 0)
            who = Participant("choice", 0, "unconstrained", self.bank.sigma, p.depth, p.beta, p.lapse,
                              risk=p.risk or None, percept=p.percept or None, hand=p.hand or None)
            self._built = (predictor, planner, spec, cohort, who)
        return self._built

    def late(self) -> Predictor:
        """The hybrid's late part: the predictor given, or the shipped CNN."""
        if self._late is None:
            from overhang_framework.plugins import Registry

            self._late = Registry().create("predictor", {"name": "cnn"}, world=self.world)
        return self._late

    def hybrid(self) -> Predictor:
        """The participant's stage-switch hybrid (:class:`overhang_builtins.hybrid.HybridPredictor`, its routing
        and its calls): the IPE of the bank early, :meth:`late` late."""
        if getattr(self, "_hybrid", None) is None:
            from overhang_builtins.hybrid import HybridPredictor

            self._hybrid = HybridPredictor(self.world, early=BankIPE(self.bank, self.params.K), late=self.late(),
                                           switch=self.params.switch)
        return self._hybrid

    def sample(self, state: State, rng: np.random.Generator) -> int:
        """The index in ``world.legal_actions(state)`` of the action the simulated participant chooses."""
        from overhang_framework.behaviour.participants import decide

        predictor, planner, spec, cohort, who = self._agent()
        choice = decide(who, spec, cohort, state, self.world, predictor, planner, self.value, rng)
        actions = self.world.legal_actions(state)
        return actions.index(choice.action)

    # --- the likelihood -----------------------------------------------------------------------------------

    def _tree(self, state: State, depth: int) -> tuple[dict, tuple]:
        """Every node of the search of ``state`` at horizon ``depth`` (by canonical key), and the root's key."""
        nodes: dict[tuple, _Node] = {}

        def visit(s: State, d: int) -> tuple:
            key = state_key(s)
            node = nodes.get(key)
            d = min(d, len(s.remaining))
            if node is None:
                actions = self.world.legal_actions(s)
                after = [self.world.successor(s, a) for a in actions]
                node = _Node(s, actions, np.array([overhang(c.geometry) for c in after], dtype=float),
                             self._answers(s, actions))
                node.after = after
                node.reach = 0
                nodes[key] = node
            if d > 1 and node.reach < d:
                node.children = [visit(c, d - 1) if not c.done else None for c in node.after]
            node.reach = max(node.reach, d)
            return key

        return nodes, visit(state, depth)

    def _answers(self, state: State, actions: list) -> np.ndarray:
        """``(len(actions), B)``: each child's verdict under each bank draw, or with a hand the hand predictor's
        weighted average of the verdicts of its shifted placements (one call: one set of columns)."""
        p = self.params
        if not actions:
            return np.zeros((0, self.bank.size))
        if p.switch and self.hybrid().route(state) == "late":  # deterministic answers: the same under every draw
            # the participant's own predictor (the hybrid, within the hand's average when it plans for one)
            answers = np.asarray(self._agent()[0].predict(state, list(actions), np.random.default_rng(0)),
                                 dtype=float)
            return np.broadcast_to(answers[:, None], (len(actions), self.bank.size))
        if not p.hand:
            return self.bank.verdicts(state, actions).astype(float)
        predictor = self._agent()[0]
        shifted = predictor.shifted(state, actions)
        verdicts = self.bank.verdicts(state, shifted).astype(float)
        return np.einsum("j,jab->ab", predictor.weights, verdicts.reshape(len(predictor.offsets), len(actions), -1))

    def _values(self, nodes: dict, key: tuple, depth: int, columns, memo: dict) -> np.ndarray:
        """``(draws,)`` values of node ``key`` at horizon ``depth`` under each draw's columns."""
        node = nodes[key]
        depth = min(depth, len(node.state.remaining))
        if (key, depth) in memo:
            return memo[(key, depth)]
        w = self._weights(node, key, columns)  # (draws, children)
        if depth <= 1:
            out = (w * node.overhang[None, :]).max(axis=1, initial=0.0)
        else:
            best = np.zeros(w.shape[0])
            for i, child in enumerate(node.children):
                tail = node.overhang[i] if child is None else self._values(nodes, child, depth - 1, columns, memo)
                np.maximum(best, w[:, i] * tail, out=best)
            out = best
        memo[(key, depth)] = out
        return out

    def _weights(self, node: _Node, key: tuple, columns) -> np.ndarray:
        """``(draws, children)``: the risk weights of the children's answers under each draw's ``K`` columns."""
        p = self.params
        idx = columns(key)  # (draws, K)
        answers = node.answers[:, idx].mean(axis=2).T  # (draws, children)
        return risk_weight(answers, p.risk, p.risk_form)

    def _root_probabilities(self, state: State, chunk: int, rng: np.random.Generator) -> np.ndarray:
        """``(chunk, n)``: under each of ``chunk`` draws, the softmax over ``state``'s root scores (no lapse)."""
        scores = self.score_samples(state, chunk, rng)
        z = self.params.beta * (scores - scores.max(axis=1, keepdims=True))
        e = np.exp(z)
        return e / e.sum(axis=1, keepdims=True)

    def score_samples(self, state: State, chunk: int, rng: np.random.Generator) -> np.ndarray:
        """``(chunk, n)``: the planner's exact root scores of ``state``'s actions under each of ``chunk`` draws of
        every node's ``K`` bank columns (no percept)."""
        p = self.params
        horizon = max(1, min(p.depth, len(state.remaining)))
        cache_key = (state_key(state), horizon)
        if cache_key not in self._trees:
            self._trees[cache_key] = self._tree(state, horizon)
        nodes, root = self._trees[cache_key]
        drawn: dict[tuple, np.ndarray] = {}

        def columns(key):
            if key not in drawn:
                drawn[key] = rng.integers(self.bank.size, size=(chunk, p.K))
            return drawn[key]

        node = nodes[root]
        w = self._weights(node, root, columns)
        if horizon <= 1:
            scores = w * node.overhang[None, :]
        else:
            memo: dict = {}
            scores = np.zeros_like(w)
            for i, child in enumerate(node.children):
                tail = node.overhang[i] if child is None else self._values(nodes, child, horizon - 1, columns, memo)
                scores[:, i] = w[:, i] * tail
        return scores

    def perceived_samples(self, state: State, draws: int, percepts: int,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`score_samples` with the percept: ``percepts`` towers seen of ``state``
        (:func:`overhang_framework.fit.percept.percepts`: standard normal draws that are a function of the state,
        the same for every model), each with an equal share of the ``draws`` samples of every node's ``K``
        columns. Returns ``(draws, m)`` root scores of the seen towers' actions (``-inf`` past a tower's
        actions) and ``(draws, m)`` the index in ``world.legal_actions(state)`` of the placement each becomes
        in the real tower (``-1`` past a tower's actions)."""
        from overhang_framework.fit.percept import percepts as seen_towers, seen_to_real

        seen = seen_towers(state, self.params.percept, int(percepts))
        shares = np.full(len(seen), int(draws) // len(seen))
        shares[: int(draws) % len(seen)] += 1
        blocks = [(self.score_samples(x, int(c), rng), seen_to_real(self.world, state, x))
                  for x, c in zip(seen, shares) if c]
        m = max(b.shape[1] for b, _ in blocks)
        scores, targets = np.full((int(draws), m), -np.inf), np.full((int(draws), m), -1, dtype=int)
        row = 0
        for block, real in blocks:
            scores[row: row + len(block), : block.shape[1]] = block
            targets[row: row + len(block), : len(real)] = real
            row += len(block)
        return scores, targets

    def _chunk(self, state: State) -> int:
        n = max(len(self.world.legal_actions(state)), 1)
        return int(max(1, min(self.draws, CHUNK_ELEMENTS // (n * self.params.K * max(self.bank.size // 50, 1)))))

    def _exact(self) -> bool:
        return self.params.K == 1 and self.params.depth == 1 and not self.params.percept

    def _samples(self, state: State, rng: np.random.Generator):
        """Chunks of per-draw softmax probabilities over the real state's actions (percepts mapped back)."""
        p = self.params
        total = self.draws
        chunk = self._chunk(state)
        done = 0
        while done < total:
            m = min(chunk, total - done)
            if not p.percept:
                yield self._root_probabilities(state, m, rng)
            else:
                yield self._perceived(state, m, rng)
            done += m

    def _perceived(self, state: State, m: int, rng: np.random.Generator) -> np.ndarray:
        """``(m, n)``: for each draw a percept of ``state`` and the softmax over its actions, mapped onto the
        real state's actions (a seen placement the real tower does not allow becomes its nearest legal one)."""
        from overhang_framework.perception import perceive
        from overhang_framework.fit.percept import seen_to_real

        n = len(self.world.legal_actions(state))
        out = np.zeros((m, n))
        for j in range(m):
            seen = perceive(state, self.params.percept, rng)
            probs = self._root_probabilities(seen, 1, rng)[0]
            np.add.at(out[j], seen_to_real(self.world, state, seen), probs)
            if seen is not state:
                self._trees.pop((state_key(seen), max(1, min(self.params.depth, len(seen.remaining)))), None)
        return out

    def prob(self, state: State) -> np.ndarray:
        """The probability of each of ``world.legal_actions(state)`` (see the module docstring)."""
        return self._prob(state)[0]

    def prob_error(self, state: State) -> np.ndarray:
        """The Monte Carlo standard error of each probability of :meth:`prob` (0 where it is exact)."""
        return self._prob(state)[1]

    def _prob(self, state: State) -> tuple[np.ndarray, np.ndarray]:
        key = state_key(state)
        kept = getattr(self, "_probs", {})
        self._probs = kept
        if key in kept:
            return kept[key]
        p = self.params
        n = len(self.world.legal_actions(state))
        if self._exact():
            node_nodes, root = self._tree(state, 1)
            node = node_nodes[root]
            w = risk_weight(node.answers.T, p.risk, p.risk_form)  # (B, n): every column once
            scores = w * node.overhang[None, :]
            e = np.exp(p.beta * (scores - scores.max(axis=1, keepdims=True)))
            mean = (e / e.sum(axis=1, keepdims=True)).mean(axis=0)
            error = np.zeros(n)
        else:
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0xC401CE, *_words(key)]))
            total, square, count = np.zeros(n), np.zeros(n), 0
            for probs in self._samples(state, rng):
                total += probs.sum(axis=0)
                square += (probs ** 2).sum(axis=0)
                count += probs.shape[0]
            mean = total / count
            error = np.sqrt(np.maximum(square / count - mean ** 2, 0.0) / count)
        out = ((1 - p.lapse) * mean + p.lapse / n, (1 - p.lapse) * error)
        kept[key] = out
        return out


def fixed_draw_prob(choice: BankChoice, state: State, seed: int = 0, percepts: int = 8) -> np.ndarray:
    """The likelihood the fit's score tables give (before the participant's own noise entered it): one fixed
    draw of every node's ``K`` bank columns (common random numbers, a function of ``seed`` and the node), the
    softmax over those root scores, the lapse; with a percept, the average of ``percepts`` such tables of
    percepts drawn from ``seed``."""
    p = choice.params
    n = len(choice.world.legal_actions(state))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xF1BED, *_words(state_key(state))]))
    if p.percept:
        from overhang_framework.perception import perceive
        from overhang_framework.fit.percept import seen_to_real

        out = np.zeros(n)
        for _ in range(percepts):
            seen = perceive(state, p.percept, rng)
            probs = choice._root_probabilities(seen, 1, rng)[0]
            np.add.at(out, seen_to_real(choice.world, state, seen), probs / percepts)
        mean = out
    else:
        mean = choice._root_probabilities(state, 1, rng)[0]
    return (1 - p.lapse) * mean + p.lapse / n


def _words(key: tuple) -> list[int]:
    import hashlib

    digest = hashlib.blake2b(repr(key).encode(), digest_size=8).digest()
    return [int.from_bytes(digest[:4], "little"), int.from_bytes(digest[4:], "little")]


def g_test(counts: np.ndarray, probs: np.ndarray, min_expected: float = 5.0) -> tuple[float, int, float]:
    """The G-test of observed ``counts`` against probabilities ``probs``: ``(G, degrees of freedom, p)``.

    Cells whose expected count is below ``min_expected`` are pooled into one (the chi-square approximation
    needs expected counts of a few); a choice the probabilities call impossible (expected 0, observed > 0)
    gives ``p = 0``.
    """
    from scipy.stats import chi2

    counts = np.asarray(counts, dtype=float)
    probs = np.asarray(probs, dtype=float)
    total = counts.sum()
    expected = probs / probs.sum() * total
    if np.any((expected <= 0) & (counts > 0)):
        return math.inf, int(np.sum(expected > 0)), 0.0
    obs, exp = _pooled(counts, expected, expected < min_expected)
    g = 2.0 * _relative_entropy(obs, exp)
    dof = max(int(len(obs)) - 1, 1)
    return g, dof, float(chi2.sf(g, dof))


def _pooled(x: np.ndarray, reference: np.ndarray, small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x`` and ``reference`` with the cells marked ``small`` summed into one, and the cells whose reference is
    0 left out."""
    if small.any():
        x = np.append(x[~small], x[small].sum())
        reference = np.append(reference[~small], reference[small].sum())
    keep = reference > 0
    return x[keep], reference[keep]


def _relative_entropy(x: np.ndarray, reference: np.ndarray) -> float:
    """``sum x log(x / reference)`` over the cells where ``x`` is positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.sum(np.where(x > 0, x * np.log(x / reference), 0.0)))


def g_power(probs: np.ndarray, alternative: np.ndarray, n: int, alpha: float, min_expected: float = 5.0) -> float:
    """The power of :func:`g_test` at ``alpha`` with ``n`` choices drawn from ``probs`` to reject ``alternative``:
    the noncentral chi-square approximation, noncentrality ``2 n KL(probs || alternative)`` over the test's
    cells (an ``alternative`` that calls a likely choice impossible is rejected for sure)."""
    from scipy.stats import chi2, ncx2

    probs = np.asarray(probs, dtype=float)
    alt = np.asarray(alternative, dtype=float)
    alt = alt / alt.sum()
    expected = alt * n
    if np.any((alt <= 0) & (probs * n >= 1)):
        return 1.0
    p, q = _pooled(probs, alt, expected < min_expected)
    kl = _relative_entropy(p, q)
    dof = max(int(len(q)) - 1, 1)
    return float(ncx2.sf(chi2.isf(alpha, dof), dof, max(2 * n * kl, 1e-12)))


def holm(pvalues: Sequence[float], alpha: float) -> list[bool]:
    """Which of ``pvalues`` Holm's step-down procedure rejects at family-wise level ``alpha``."""
    order = np.argsort(pvalues, kind="stable")
    reject = [False] * len(pvalues)
    m = len(pvalues)
    for rank, i in enumerate(order):
        if pvalues[i] <= alpha / (m - rank):
            reject[i] = True
        else:
            break
    return reject
