"""The four interfaces every model is built from: World, Predictor, Planner, Value.

Implementations are plugins (see :mod:`overhang_framework.hookspecs`); the core
only ever talks to these abstract classes.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from overhang_framework.errors import IllegalActionError
from overhang_framework.geometry import Action, Geometry


@dataclass(frozen=True)
class Task:
    """A block sequence; ``sequence[0]`` is the ground block, the rest are placed in order."""

    id: str
    sequence: tuple[float, ...]


@dataclass(frozen=True)
class State:
    """A decision state: the placed geometry and the widths still to place."""

    geometry: Geometry
    remaining: tuple[float, ...]

    @property
    def next_width(self) -> Optional[float]:
        return self.remaining[0] if self.remaining else None

    @property
    def done(self) -> bool:
        return not self.remaining


@dataclass
class Budget:
    """What a planner may spend on one decision; ``None`` means no limit.

    ``seconds`` is wall-clock time; ``predictor_calls`` is a machine-independent
    budget of batched predictor calls (one call scores all the children of one
    state), which keeps budgeted runs reproducible by seed. A planner records
    each call with :meth:`charge`. ``observer``, when set, is called with the
    budget after each charge: how the run shows a long decision's progress.
    """

    seconds: Optional[float] = None
    predictor_calls: Optional[int] = None
    started: float = field(default_factory=time.perf_counter, repr=False)
    calls_used: int = 0
    observer: Optional[Callable[["Budget"], None]] = field(default=None, repr=False, compare=False)

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def charge(self, calls: int = 1) -> None:
        """Record ``calls`` predictor calls."""
        self.calls_used += calls
        if self.observer is not None:
            self.observer(self)

    def exhausted(self) -> bool:
        return (self.seconds is not None and self.elapsed() >= self.seconds) or (
            self.predictor_calls is not None and self.calls_used >= self.predictor_calls)

    @property
    def limited(self) -> bool:
        return self.seconds is not None or self.predictor_calls is not None


@dataclass
class Spend:
    """What a decision cost.

    ``nodes_expanded`` counts states whose children were scored;
    ``leaves_pruned`` counts children a search skipped because a bound proved
    they could not change its answer; ``depth_completed`` is the deepest
    search horizon finished (``None`` for planners without one); ``iterations``
    counts simulations of sampling planners.
    """

    predictor_calls: int = 0
    actions_scored: int = 0
    nodes_expanded: int = 0
    seconds: float = 0.0
    budget_exhausted: bool = False
    leaves_pruned: int = 0
    depth_completed: Optional[int] = None
    iterations: int = 0


@dataclass
class Decision:
    """A planner's choice, the predicted stability of the resulting tower, and what it cost.

    ``choice_probability`` is the probability the planner's choice rule gave
    the chosen action, and ``choice_rank`` its rank by the planner's score (1
    is best; tied actions share a rank): what a likelihood analysis needs.
    """

    action: Action
    predicted_stability: float
    spend: Spend = field(default_factory=Spend)
    choice_probability: float = 1.0
    choice_rank: int = 1


class World(abc.ABC):
    """Rules and physics of a tower-building task."""

    @abc.abstractmethod
    def initial_state(self, task: Task) -> State:
        """The state with the task's first block at the ground centre."""

    @abc.abstractmethod
    def legal_actions(self, state: State, resolution: Optional[float] = None) -> list[Action]:
        """Legal placements of the next block with x on a grid of step ``resolution``."""

    @abc.abstractmethod
    def illegal_reason(self, state: State, action: Action) -> Optional[str]:
        """Why ``action`` is illegal in ``state``, or ``None`` when it is legal (any real x)."""

    def is_legal(self, state: State, action: Action) -> bool:
        return self.illegal_reason(state, action) is None

    @abc.abstractmethod
    def successor(self, state: State, action: Action) -> State:
        """The state after ``action``, without checking that it is legal (for search)."""

    def step(self, state: State, action: Action) -> State:
        """The successor state of a legal action; raises :class:`IllegalActionError` otherwise."""
        reason = self.illegal_reason(state, action)
        if reason is not None:
            raise IllegalActionError(f"illegal action (x={action.x:g}, layer={action.layer}): {reason}")
        return self.successor(state, action)

    @abc.abstractmethod
    def is_stable(self, geometry: Geometry) -> bool:
        """Ground-truth stability of ``geometry``."""

    @abc.abstractmethod
    def overhang(self, geometry: Geometry) -> float:
        """The task objective of a geometry."""

    def reward(self, geometry: Geometry, stable_throughout: bool) -> float:
        """The final overhang if the tower was stable after every placement, else 0."""
        return self.overhang(geometry) if stable_throughout else 0.0

    def stats(self) -> dict:
        """Counters worth reporting with a run's results (e.g. physics cache hits); empty by default."""
        return {}


class Predictor(abc.ABC):
    """Estimates the probability that the tower stands after each candidate action."""

    #: True when the answers never depend on ``rng`` (the same state and actions give the same numbers for any
    #: generator): searches with different draw seeds then get the same answers, and fits share their tables.
    deterministic: bool = False

    @abc.abstractmethod
    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        """Probabilities in [0, 1], one per action, from one batched call."""

    def predict_many(self, requests: Sequence[tuple[State, Sequence[Action]]],
                     rngs: Sequence[np.random.Generator]) -> list[np.ndarray]:
        """:meth:`predict` for several ``(state, actions)`` requests, each with its own generator.

        Each result must equal ``predict(state, actions, rng)``; a predictor
        that can serve them together (one physics call, one forward pass)
        overrides this to be faster. Searches use it to score many states at once.
        """
        return [self.predict(state, actions, rng) for (state, actions), rng in zip(requests, rngs)]


class Value(abc.ABC):
    """Scores a search leaf. Values are >= 0 (a collapse is worth 0)."""

    @abc.abstractmethod
    def __call__(self, state: State) -> float:
        """The value of ``state``."""

    def bound(self, state: State, depth: int) -> Optional[float]:
        """An upper bound on the value of every state reachable from ``state`` in ``depth``
        placements (``depth = 0``: ``state`` itself), or ``None`` when there is none.

        Searches prune with it, so it must never be below a reachable value;
        a loose bound only costs speed.
        """
        return None


class Planner(abc.ABC):
    """Chooses the next action."""

    @abc.abstractmethod
    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        """The next action from ``state`` within ``budget``, with what it spent."""
