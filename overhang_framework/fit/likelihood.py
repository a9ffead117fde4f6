"""The likelihood of a participant's placements under a model: a softmax over score tables, mixed with a lapse.

For a decision state ``s`` with legal grid actions ``a_1 .. a_n`` and the
model's scores ``S_i`` (its :mod:`score tables <overhang_framework.fit.scores>`),
the probability of action ``a_i`` is::

    P(a_i) = (1 - lapse) * exp(beta * S_i) / sum_j exp(beta * S_j) + lapse / n

``beta`` is the inverse temperature per metre of score, ``lapse`` the
probability of a uniformly random legal action (the simulated participants'
choice rule, :mod:`overhang_framework.behaviour.participants`).

**Mapping a placement onto the grid.** A person's ``x`` is continuous; the model
chooses among the world's grid of x at the logged ``layer``. The placement is
mapped to the legal grid action of that layer nearest to ``x`` (ties: the
smaller x), when it is at most one grid step (``world.resolution``) away.
A placement with no legal grid action of its layer within a step (possible for a
person squeezing a block into a gap the grid does not reach) is *unmapped*: it
is left out of the likelihood, and counted in ``fits.csv`` (``unmapped``).
Timed-out records place nothing and are left out too.

**With a motor model** (the fit's ``motor``, :mod:`overhang_framework.fit.motor`) a placement is not mapped:
its probability is that of its x given each legal grid action the participant may have planned,
``P(x) = sum_i P(a_i) W_i``, the lapse's uniform action included, and only a placement no grid action of its
layer can reach is left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from overhang_framework.interfaces import State, World


def action_index(world: World, state: State, x: float, layer: int) -> Optional[int]:
    """The index in ``world.legal_actions(state)`` of the grid action a placement at ``(x, layer)`` maps to."""
    actions = world.legal_actions(state)
    best, gap = None, None
    for i, a in enumerate(actions):
        if a.layer != layer:
            continue
        d = abs(a.x - x)
        if gap is None or d < gap - 1e-12:
            best, gap = i, d
    if best is None or gap > world.resolution + 1e-9:
        return None
    return best


@dataclass
class Decisions:
    """A participant's decisions under one model: score tables padded into one array, and the chosen indices.

    ``scores`` is ``(n, m)`` with ``-inf`` past each table's ``sizes``; ``chosen``
    the index of each executed action. With a motor model (:mod:`overhang_framework.fit.motor`) ``weights``
    ``(n, m)`` holds, for every legal action, the probability that a placement planned as it lands where the
    executed one did; a decision's probability is then ``sum_j P(a_j) weights_j`` (None: the chosen action's).
    """

    scores: np.ndarray
    sizes: np.ndarray
    chosen: np.ndarray
    weights: Optional[np.ndarray] = None

    @classmethod
    def of(cls, tables: Sequence[np.ndarray], chosen: Sequence[int],
           weights: Optional[Sequence[np.ndarray]] = None) -> "Decisions":
        n = len(tables)
        m = max((len(t) for t in tables), default=1)
        scores = np.full((n, m), -np.inf)
        for i, t in enumerate(tables):
            scores[i, : len(t)] = t
        return cls(scores, np.array([len(t) for t in tables], dtype=float), np.asarray(chosen, dtype=int),
                   padded_weights(weights, m))

    def __len__(self) -> int:
        return len(self.chosen)

    def subset(self, rows: np.ndarray) -> "Decisions":
        return Decisions(self.scores[rows], self.sizes[rows], self.chosen[rows],
                         None if self.weights is None else self.weights[rows])

    def concat(self, other: "Decisions") -> "Decisions":
        if (self.weights is None) != (other.weights is None):
            raise ValueError("cannot join decisions with a motor model to decisions without one")
        m = max(self.scores.shape[1], other.scores.shape[1])
        pad = lambda s, v: np.pad(s, ((0, 0), (0, m - s.shape[1])), constant_values=v)  # noqa: E731
        weights = None if self.weights is None else np.vstack([pad(self.weights, 0.0), pad(other.weights, 0.0)])
        return Decisions(np.vstack([pad(self.scores, -np.inf), pad(other.scores, -np.inf)]),
                         np.concatenate([self.sizes, other.sizes]), np.concatenate([self.chosen, other.chosen]),
                         weights)


def padded_weights(weights: Optional[Sequence[np.ndarray]], m: int) -> Optional[np.ndarray]:
    """A motor model's weights of each decision (one array a decision) padded with zeros into ``(n, m)``; None
    stays None."""
    if weights is None:
        return None
    out = np.zeros((len(weights), m))
    for i, w in enumerate(weights):
        out[i, : len(w)] = w
    return out


def decision_probabilities(decisions: "Decisions", beta: float, lapse: float) -> np.ndarray:
    """Each decision's probability of what was done: its executed grid action's, or with a motor model's weights
    its placement's (the terms :func:`log_likelihood` sums the logs of)."""
    if not isinstance(decisions, Decisions):
        return np.asarray(decisions.probabilities(beta, lapse), dtype=float)
    if len(decisions) == 0:
        return np.zeros(0)
    s = decisions.scores
    top = s.max(axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        z = np.where(np.isfinite(s), beta * (s - top), -np.inf)
    e = np.exp(z)
    soft = e / e.sum(axis=1, keepdims=True)
    if decisions.weights is not None:
        w = decisions.weights
        return (1 - lapse) * (soft * w).sum(axis=1) + lapse * w.sum(axis=1) / decisions.sizes
    return (1 - lapse) * soft[np.arange(len(decisions)), decisions.chosen] + lapse / decisions.sizes


def choice_probabilities(scores: np.ndarray, beta: float, lapse: float) -> np.ndarray:
    """``P(a_i)`` of every action of one table (see the module docstring)."""
    s = np.asarray(scores, dtype=float)
    z = beta * (s - s.max())
    w = np.exp(z)
    return (1 - lapse) * w / w.sum() + lapse / s.size


def log_likelihood(decisions: Decisions, beta: float, lapse: float) -> float:
    """The sum over decisions of ``log P(executed action)`` (of a model with perceptual noise too:
    :class:`~overhang_framework.fit.percept.PerceivedDecisions`)."""
    if not isinstance(decisions, Decisions):
        return decisions.log_likelihood(beta, lapse)
    if len(decisions) == 0:
        return 0.0
    s = decisions.scores
    top = s.max(axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        z = np.where(np.isfinite(s), beta * (s - top), -np.inf)
    if decisions.weights is not None:
        e = np.exp(z)
        w = decisions.weights
        p = (1 - lapse) * (e * w).sum(axis=1) / e.sum(axis=1) + lapse * w.sum(axis=1) / decisions.sizes
        return float(np.log(np.maximum(p, 1e-300)).sum())
    log_norm = np.log(np.exp(z).sum(axis=1))
    chosen = z[np.arange(len(decisions)), decisions.chosen] - log_norm
    p = (1 - lapse) * np.exp(chosen) + lapse / decisions.sizes
    return float(np.log(np.maximum(p, 1e-300)).sum())
