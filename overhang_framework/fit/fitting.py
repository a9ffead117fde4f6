"""Fitting models to behaviour: ``beta`` and the lapse by optimisation over score tables, ``sigma``, a
hybrid's switch point, the planner's risk aversion and the hand it plans for on grids.

A *model index* is a predictor family and a depth (``ipe/D2``, ``cnn/myopic``).
Its free parameters are the softmax's ``beta`` and the ``lapse`` (always), the
predictor's ``sigma`` when the model space gives a grid of several values
(``ipe`` by default), a hybrid's ``switch`` point likewise (``hybrid`` by default: every
switch point the tasks allow), and the ``risk``, ``hand`` and ``percept`` of their grids when given
(a percept's likelihood: :mod:`overhang_framework.fit.percept`). For each grid point the tables are fixed, so ``beta`` and
``lapse`` are fitted by L-BFGS-B (SciPy) from several starts; the grid point
with the highest likelihood is kept. Each fit reports its log-likelihood, its
number of parameters ``k`` (2, plus one for each grid of several values), the number of
placements ``n`` it explains, ``BIC = k ln n - 2 LL`` and ``AIC = 2 k - 2 LL``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np
import pandas as pd
from scipy.optimize import minimize

from overhang_framework.fit.likelihood import Decisions, action_index, log_likelihood
from overhang_framework.fit.scores import Model, ScoreTables
from overhang_framework.geometry import Block, Geometry, check_width
from overhang_framework.interfaces import State, World

#: Bounds of the fitted parameters: beta per metre of score, lapse a probability.
BETA_BOUNDS = (0.0, 200.0)
LAPSE_BOUNDS = (0.0, 1.0)
#: Starting points of the optimiser (beta, lapse); the best end point is kept.
STARTS = ((1.0, 0.05), (10.0, 0.05), (50.0, 0.05), (10.0, 0.3))


@dataclass
class Placement:
    """One executed placement of a log, as the fit sees it: its decision state and where the block went."""

    participant: str
    condition: str
    state: State
    x: float
    layer: int
    trial: int = 0
    step: int = 0


def log_placements(df: pd.DataFrame) -> list[Placement]:
    """The executed placements of a behaviour log (timed-out records left out), in the log's order."""
    out = []
    done = df[~df["timed_out"]]
    cols = ["participant", "condition", "tower_before", "sequence", "step", "width", "x", "layer", "trial"]
    for row in done[cols].itertuples(index=False):
        geometry = Geometry(tuple(Block(check_width(w), float(bx), int(bl)) for w, bx, bl in row.tower_before))
        # the sequence starts with the ground block, so the block of step k is sequence[k]
        remaining = tuple(float(w) for w in row.sequence[row.step:])
        out.append(Placement(str(row.participant), str(row.condition), State(geometry, remaining), float(row.x),
                             int(row.layer), int(row.trial), int(row.step)))
    return out


@dataclass
class Mapped:
    """Placements mapped onto the world's grid: the decision states and chosen indices, and how many were not."""

    states: list[State]
    chosen: list[int]
    unmapped: int
    #: The (participant, trial) of each mapped placement: the unit of held-out folds.
    trials: list[tuple[str, int]] = field(default_factory=list)
    #: With a motor model, each placement's ``W`` over its state's legal actions (:mod:`~overhang_framework.fit.motor`).
    weights: Optional[list[np.ndarray]] = None


#: How decision states are built: ``logged`` takes the log's towers, ``grid`` replays each trial's mapped grid actions.
STATES = ("logged", "grid")


def map_placements(world: World, placements: Sequence[Placement], states: str = "logged",
                   motor: Optional[Any] = None) -> Mapped:
    """The decision states of ``placements`` and the grid action each executed placement maps to.

    With ``states="logged"`` (the default), every decision state is the logged
    tower, as the person saw it. With ``states="grid"``, a trial's decision
    states are the model's own: the first is the logged one, and each next one is
    the previous state after the grid action the previous placement mapped to.
    Those towers are within a grid step of the logged ones and are shared by
    every participant who made the same grid choices (fewer tables), but a tower
    near its balance limit can stand on the grid and fall as logged, or the
    reverse, which the lapse then absorbs (docs/fitting.md). When a placement is
    unmapped, or a record is missing, a grid trial goes on from the logged tower.

    With ``motor`` (a :class:`~overhang_framework.fit.motor.Motor`) each placement also gets its ``W`` over the
    legal actions; it is kept when some grid action of its layer can reach it (its nearest grid action, or the
    action most likely to have put it there, stands as ``chosen`` for the statistics that need one).
    """
    if states not in STATES:
        raise ValueError(f"unknown decision states {states!r}; allowed: {', '.join(STATES)}")
    from overhang_framework.fit.motor import weights as motor_weights

    out, chosen, trials, unmapped, weights = [], [], [], 0, []
    after: dict[tuple, State] = {}  # (participant, trial) -> the grid state after its last mapped placement
    for p in placements:
        state = p.state
        trial = (p.participant, p.trial)
        replayed = after.pop(trial, None) if states == "grid" else None
        if replayed is not None and len(replayed.geometry) == len(p.state.geometry):
            state = State(replayed.geometry, p.state.remaining)
        index = action_index(world, state, p.x, p.layer)
        if motor is not None:
            w = motor_weights(world, state, p.x, p.layer, motor)
            if not (w > 0).any():
                unmapped += 1
                continue
            weights.append(w)
            index = int(np.argmax(w)) if index is None else index
        if index is None:
            unmapped += 1
            continue
        out.append(state)
        chosen.append(index)
        trials.append((p.participant, p.trial))
        if states == "grid":
            after[trial] = world.successor(state, world.legal_actions(state)[index])
    return Mapped(out, chosen, unmapped, trials, weights if motor is not None else None)


@dataclass
class SoftmaxFit:
    beta: float
    lapse: float
    loglik: float


def fit_softmax(decisions: Decisions) -> SoftmaxFit:
    """The ``beta`` and ``lapse`` of highest likelihood for fixed score tables."""
    if len(decisions) == 0:
        return SoftmaxFit(float("nan"), float("nan"), 0.0)

    gradient = getattr(decisions, "value_and_grad", None)

    def objective(theta):
        return -log_likelihood(decisions, float(theta[0]), float(theta[1]))

    def with_gradient(theta):
        value, grad = gradient(float(theta[0]), float(theta[1]))
        return -value, -grad

    best = None
    for start in STARTS:
        res = minimize(objective if gradient is None else with_gradient, np.array(start), method="L-BFGS-B",
                       jac=gradient is not None, bounds=[BETA_BOUNDS, LAPSE_BOUNDS])
        if best is None or res.fun < best.fun:
            best = res
    return SoftmaxFit(float(best.x[0]), float(best.x[1]), -float(best.fun))


@dataclass
class ModelFit:
    """A model index fitted to one participant (or a pooled group)."""

    participant: str
    condition: str
    label: str
    family: str
    depth: int
    sigma: Optional[float]
    beta: float
    lapse: float
    loglik: float
    k: int
    n: int
    unmapped: int
    switch: Optional[int] = None
    #: The planner's risk aversion of the best grid point (0, risk-neutral, for a model without a risk grid).
    risk: Optional[float] = None
    #: The motor noise the best grid point plans for (0, none, for a model without a hand grid).
    hand: Optional[float] = None
    #: The perceptual noise of the best grid point (0, none, for a model without a percept grid).
    percept: Optional[float] = None
    #: Held-out log-likelihood summed over the folds of a cross-validation (None: not cross-validated).
    heldout: Optional[float] = None
    folds: Optional[int] = None

    @property
    def bic(self) -> float:
        return self.k * math.log(self.n) - 2 * self.loglik if self.n else float("nan")

    @property
    def aic(self) -> float:
        return 2 * self.k - 2 * self.loglik

    def row(self) -> dict:
        return {"participant": self.participant, "condition": self.condition, "model": self.label,
                "family": self.family, "depth": self.depth, "sigma": self.sigma, "switch": self.switch,
                "risk": self.risk, "hand": self.hand, "percept": self.percept, "beta": self.beta,
                "lapse": self.lapse, "loglik": self.loglik, "k": self.k, "n": self.n, "bic": self.bic,
                "aic": self.aic, "unmapped": self.unmapped, "heldout_loglik": self.heldout, "folds": self.folds}


def fold_of(trials: Sequence[tuple[str, int]], folds: int, seed: int = 0) -> np.ndarray:
    """The fold (0 .. ``folds - 1``) of each placement's trial: each participant's trials, sorted, are dealt
    into the folds in an order drawn from ``(seed, participant)``, so that the folds are as even as the
    trials allow, a trial's placements stay together, and a participant's folds are the same in their own
    fit and in a pooled one, whatever the order of the log."""
    import hashlib

    assigned: dict[tuple[str, int], int] = {}
    by_participant: dict[str, list[int]] = {}
    for participant, trial in trials:
        by_participant.setdefault(str(participant), []).append(int(trial))
    for participant, numbers in by_participant.items():
        numbers = sorted(set(numbers))
        word = int.from_bytes(hashlib.blake2b(participant.encode(), digest_size=8).digest(), "little")
        order = np.random.default_rng(np.random.SeedSequence([int(seed), word])).permutation(len(numbers))
        for rank, i in enumerate(order):
            assigned[(participant, numbers[int(i)])] = rank % folds
    return np.array([assigned[(str(p), int(t))] for p, t in trials], dtype=int)


def _decisions(tables: ScoreTables, mapped: Mapped) -> Decisions:
    if not tables.model.percept:
        return Decisions.of([tables.table(s) for s in mapped.states], mapped.chosen, mapped.weights)
    from overhang_framework.fit.percept import perceived_decisions

    return perceived_decisions(tables, mapped.states, mapped.chosen, tables.model.percept, mapped.weights)


def _best(decisions: Sequence[Decisions]) -> tuple[SoftmaxFit, int]:
    """The softmax fit of highest likelihood over the grid points' ``decisions``, and its index."""
    best, which = None, 0
    for k, d in enumerate(decisions):
        fit = fit_softmax(d)
        if best is None or fit.loglik > best.loglik + 1e-9:
            best, which = fit, k
    return best, which


def heldout_loglik(variants: Sequence[ScoreTables], mapped: Mapped, folds: int, seed: int = 0) -> float:
    """The log-likelihood of each fold's placements under the model index fitted (grid point, ``beta``,
    ``lapse``) to the other folds, summed over the folds. NaN when some placement cannot be scored so (all of
    them in one fold: a participant with one trial), or when there is none."""
    return _heldout([_decisions(t, mapped) for t in variants], mapped.trials, folds, seed)


def _heldout(every: Sequence[Decisions], trials: Sequence[tuple[str, int]], folds: int, seed: int) -> float:
    """:func:`heldout_loglik` from each grid point's decisions of the placements of ``trials``."""
    fold = fold_of(trials, folds, seed)
    if not fold.size:
        return float("nan")
    total = 0.0
    for k in range(folds):
        test, train = np.flatnonzero(fold == k), np.flatnonzero(fold != k)
        if not test.size:
            continue
        if not train.size:
            return float("nan")
        fit, which = _best([_subset(d, train) for d in every])
        total += log_likelihood(_subset(every[which], test), fit.beta, fit.lapse)
    return total


def _subset(d: Decisions, rows: np.ndarray) -> Decisions:
    return d.subset(rows)


def fit_index(participant: str, condition: str, variants: Sequence[Any], mapped: Mapped,
              folds: int = 0, seed: int = 0) -> ModelFit:
    """Fit one model index, whose ``variants`` are its score tables on the sigma and switch grids (one when
    neither is fitted). With ``folds >= 2`` the fit also reports its held-out log-likelihood
    (:func:`heldout_loglik`)."""
    every = [_decisions(t, mapped) for t in variants]
    best, which = _best(every)
    model = variants[which].model
    grids = [len({getattr(t.model, name) for t in variants}) > 1
             for name in ("sigma", "switch", "risk", "hand", "percept")]
    heldout = _heldout(every, mapped.trials, folds, seed) if folds >= 2 else None
    return ModelFit(participant, condition, model.label, model.family, model.depth, model.sigma, best.beta,
                    best.lapse, best.loglik, 2 + sum(grids), len(mapped.states), mapped.unmapped, model.switch,
                    model.risk, model.hand, model.percept, heldout, folds if folds >= 2 else None)
