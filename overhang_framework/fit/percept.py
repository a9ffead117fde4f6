"""Perceptual noise in the fit: each decision's choice probabilities averaged over the towers a participant may
have seen.

A simulated participant with perceptual noise ``percept`` sees, at each decision, the placed blocks (all but
the first) at ``x + N(0, percept^2)`` (:func:`overhang_framework.behaviour.participants.perceive`), plans on
that tower, and places in the real one: a choice the real tower does not allow becomes its nearest legal
placement. So the probability of a placement ``a`` in the real state ``s`` is::

    P(a) = (1 - lapse) * E_seen[ sum_{a' -> a} softmax_beta(S(seen))_{a'} ] + lapse / n

where ``a' -> a`` are the actions of the seen tower that become ``a`` in the real one and ``n`` the real
state's number of legal actions. The fit estimates the expectation with ``draws`` percepts of each decision
state, drawn from a generator seeded by the state's canonical key and the draw's number: the same standard
normal draws for every ``percept`` of a grid (common random numbers, as the IPE's ``sigma``), so the
likelihood is a deterministic function of the model, smooth in ``percept``. A seen tower is an ordinary
state: its score table is the model's own, computed and cached as any other.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from overhang_framework.interfaces import State, World
from overhang_framework.search import state_key

#: Percepts the fit draws of each decision state (its Monte Carlo estimate of the average).
DRAWS = 8


def percept_draws(state: State, draws: int) -> np.ndarray:
    """The standard normal draws of ``state``'s percepts: ``(draws, blocks - 1)``, a function of the state."""
    word = hashlib.blake2b(repr(state_key(state)).encode(), digest_size=8).digest()
    rng = np.random.default_rng(np.random.SeedSequence([int.from_bytes(word, "little"), 0x7E4C]))
    return rng.standard_normal((int(draws), max(len(state.geometry.blocks) - 1, 0)))


def percepts(state: State, percept: float, draws: int = DRAWS) -> list[State]:
    """The ``draws`` towers a participant with perceptual noise ``percept`` (metres) may see in ``state``."""
    from overhang_framework.perception import perceive_with

    if percept <= 0 or len(state.geometry.blocks) < 2:
        return [state] * int(draws)
    return [perceive_with(state, percept, z) for z in percept_draws(state, draws)]


def seen_to_real(world: World, state: State, seen: State) -> np.ndarray:
    """For each legal action of ``seen`` (in ``world.legal_actions(seen)``'s order), the index in
    ``world.legal_actions(state)`` of the placement it becomes in the real tower."""
    from overhang_framework.perception import nearest_legal

    real = world.legal_actions(state)
    index = {(a.x, a.layer): i for i, a in enumerate(real)}
    out = []
    for a in world.legal_actions(seen):
        i = index.get((a.x, a.layer))
        if i is None:
            b = nearest_legal(world, state, a)
            i = index[(b.x, b.layer)]
        out.append(i)
    return np.asarray(out, dtype=int)


@dataclass
class PerceivedDecisions:
    """A participant's decisions under a model with perceptual noise: the score tables of each decision's
    percepts, padded into ``scores`` ``(n, draws, m)`` (``-inf`` past each table), ``hit`` ``(n, draws, m)``
    (the seen action becomes the executed one), and ``sizes`` the real states' numbers of legal actions."""

    scores: np.ndarray
    hit: np.ndarray
    sizes: np.ndarray
    #: With a motor model, each decision's lapse weight ``sum_j W_j / n`` (None: ``1 / n``); ``hit`` is then ``W``
    #: of the real action each seen action becomes.
    lapse_weight: Optional[np.ndarray] = None

    @classmethod
    def of(cls, tables: Sequence[Sequence[np.ndarray]], targets: Sequence[Sequence[np.ndarray]],
           chosen: Sequence[int], sizes: Sequence[int],
           weights: Optional[Sequence[np.ndarray]] = None) -> "PerceivedDecisions":
        """From each decision's percepts' tables and their actions' real indices (:func:`seen_to_real`); with
        ``weights`` (a motor model's ``W`` of each decision's real actions) the executed x's probability."""
        n = len(tables)
        k = max((len(t) for t in tables), default=1)
        m = max((len(x) for t in tables for x in t), default=1)
        scores = np.full((n, k, m), -np.inf)
        hit = np.zeros((n, k, m), dtype=bool if weights is None else float)
        for i, (row, target) in enumerate(zip(tables, targets)):
            for j, (table, real) in enumerate(zip(row, target)):
                scores[i, j, : len(table)] = table
                real = np.asarray(real, dtype=int)
                hit[i, j, : len(real)] = real == int(chosen[i]) if weights is None else np.asarray(weights[i])[real]
        sizes = np.asarray(sizes, dtype=float)
        lapse_weight = None if weights is None else np.array([np.sum(w) for w in weights]) / sizes
        return cls(scores, hit, sizes, lapse_weight)

    def __len__(self) -> int:
        return len(self.sizes)

    def subset(self, rows: np.ndarray) -> "PerceivedDecisions":
        return PerceivedDecisions(self.scores[rows], self.hit[rows], self.sizes[rows],
                                  None if self.lapse_weight is None else self.lapse_weight[rows])

    def probabilities(self, beta: float, lapse: float) -> np.ndarray:
        """Each decision's probability of its executed action."""
        s = self.scores
        top = s.max(axis=2, keepdims=True)
        with np.errstate(invalid="ignore"):
            z = np.where(np.isfinite(s), beta * (s - top), -np.inf)
        w = np.exp(z)
        seen = (w * self.hit).sum(axis=2) / w.sum(axis=2)
        uniform = 1.0 / self.sizes if self.lapse_weight is None else self.lapse_weight
        return (1 - lapse) * seen.mean(axis=1) + lapse * uniform

    def log_likelihood(self, beta: float, lapse: float) -> float:
        if len(self) == 0:
            return 0.0
        return float(np.log(np.maximum(self.probabilities(beta, lapse), 1e-300)).sum())


def perceived_decisions(tables, states: Sequence[State], chosen: Sequence[int], percept: float,
                        weights: Optional[Sequence[np.ndarray]] = None) -> PerceivedDecisions:
    """The decisions of ``states`` (with the executed actions' indices ``chosen``, or a motor model's ``weights``)
    of a participant with perceptual noise ``percept``, scored with ``tables`` (the model's without the percept;
    with ``table`` and ``world``)."""
    world = tables.world
    seen = [percepts(s, percept) for s in states]
    return PerceivedDecisions.of([[tables.table(x) for x in row] for row in seen],
                                 [[seen_to_real(world, s, x) for x in row] for s, row in zip(states, seen)],
                                 chosen, [len(world.legal_actions(s)) for s in states], weights)
