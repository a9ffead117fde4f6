"""What plays the benchmark, and one episode of it under the protocol.

An episode is one attempt at a task: the agent places each block of the sequence in turn, choosing
among the legal placements on the world's grid; the world (its default physics: the reference's
verdicts) checks the tower after every placement, and the first collapse ends the episode with
reward 0. Otherwise the reward is the final overhang. Every agent plays through :func:`play`:

* :class:`PlannerAgent`: any planner plugin with any predictor and value (``planner=... predictor=...``),
  ``planner=policy`` for a trained policy. A decision's budget is the ladder's rung: predictor calls
  (``Budget.predictor_calls``) or seconds (``Budget.seconds``). An action off the grid (a policy's
  continuous x) is played as the nearest legal placement, and counted;
* :class:`RandomAgent`: a legal placement drawn uniformly;
* :class:`~overhang_framework.benchmark.external.CommandAgent`: a program in any language, speaking
  JSON Lines over stdin and stdout (docs/benchmark-protocol.md).

An agent that fails (a crash, a timeout, an answer that does not parse or is not a legal placement)
ends that episode with reward 0 and a reason; the run goes on.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from overhang_framework.geometry import Action
from overhang_framework.interfaces import Budget, State, Task, World

#: Budget kinds: predictor calls per decision, seconds per decision.
BUDGET_KINDS = ("calls", "seconds")


class AgentFailed(Exception):
    """The agent could not give a legal answer; the message is the episode's reason."""


@dataclass
class Choice:
    """One decision: the action, and what the agent spent on it (``calls``: predictor calls, if it counts them)."""

    action: Action
    calls: Optional[int] = None
    snapped: bool = False


def task_number(task_id: str) -> int:
    """A task's number for its episode generator: the digits of its id (every id has its own)."""
    digits = "".join(c for c in task_id if c.isdigit())
    return int(digits) if digits else 0


def episode_generator(task_id: str, seed: int) -> np.random.Generator:
    """The generator of the episode of ``task_id`` with ``seed``, whatever else the run plays."""
    from overhang_framework.episode import episode_rng

    return episode_rng(seed, task_number(task_id), 0)


def on_grid(state: State, action: Any, world: World) -> tuple[Optional[Action], Optional[str]]:
    """The legal grid placement ``action`` names (x within 1e-6, the same layer), or why there is none."""
    legal = world.legal_actions(state)
    for a in legal:
        if a.layer == action.layer and abs(a.x - action.x) <= 1e-6:
            return a, None
    why = world.illegal_reason(state, action)
    if why is None:
        why = f"x={action.x:g} is not on the world's grid of {getattr(world, 'resolution', 0.1):g}"
    return None, f"illegal placement x={action.x:g}, layer={action.layer}: {why}"


def nearest_legal(state: State, action: Action, world: World) -> Action:
    """The legal grid placement nearest ``action`` (its own layer first)."""
    legal = world.legal_actions(state)
    return min(legal, key=lambda a: (a.layer != action.layer, abs(a.layer - action.layer), abs(a.x - action.x)))


class Agent(abc.ABC):
    """Chooses placements; :func:`play` runs its episodes."""

    #: ``"calls"`` or ``"seconds"`` when the agent honours a budget per decision; ``None`` when it takes none.
    budget_kind: Optional[str] = None
    #: Whether the agent counts its predictor calls (an episode of one that does not records none).
    counts_calls: bool = True

    def start(self, task: Task, seed: int, budget: Optional[float]) -> None:
        """A new episode begins."""

    @abc.abstractmethod
    def choose(self, state: State, task: Task, step: int, budget: Optional[float]) -> Choice:
        """The placement of block ``step`` (1 for the first block after the ground block)."""

    def end(self, task: Task, seed: int, record: dict) -> None:
        """The episode ended with ``record``."""

    def close(self) -> None:
        """The run is over."""


class PlannerAgent(Agent):
    """A planner plugin with its predictor and value."""

    def __init__(self, models: dict, budget_kind: str = "calls"):
        if budget_kind not in BUDGET_KINDS:
            raise ValueError(f"unknown budget kind {budget_kind!r}; allowed: {', '.join(BUDGET_KINDS)}")
        self.world, self.predictor = models["world"], models["predictor"]
        self.planner, self.value = models["planner"], models["value"]
        self.budget_kind = budget_kind
        self.rng: Optional[np.random.Generator] = None

    def start(self, task: Task, seed: int, budget: Optional[float]) -> None:
        self.rng = episode_generator(task.id, seed)

    def choose(self, state: State, task: Task, step: int, budget: Optional[float]) -> Choice:
        limit = Budget(seconds=budget if self.budget_kind == "seconds" else None,
                       predictor_calls=int(budget) if budget is not None and self.budget_kind == "calls" else None)
        decision = self.planner.plan(state, self.predictor, self.value, limit, self.rng)
        action, why = on_grid(state, decision.action, self.world)
        snapped = action is None
        if snapped:
            action = nearest_legal(state, decision.action, self.world)
        return Choice(action, int(decision.spend.predictor_calls), snapped)


class RandomAgent(Agent):
    """A legal grid placement drawn uniformly, from the episode's generator."""

    def __init__(self, world: World):
        self.world = world
        self.rng: Optional[np.random.Generator] = None

    def start(self, task: Task, seed: int, budget: Optional[float]) -> None:
        self.rng = episode_generator(task.id, seed)

    def choose(self, state: State, task: Task, step: int, budget: Optional[float]) -> Choice:
        legal = self.world.legal_actions(state)
        return Choice(legal[int(self.rng.integers(len(legal)))], 0)


def play(agent: Agent, world: World, task: Task, seed: int, budget: Optional[float] = None) -> dict:
    """One episode of ``task`` by ``agent``: its record, with ``reward``, ``stood``, ``calls``, ``seconds``
    and ``reason`` (empty when the tower stood to the end)."""
    state = world.initial_state(task)
    steps: list = []
    reason = ""
    agent.start(task, seed, budget)
    stood = True
    step = 0
    failed_seconds = 0.0  # the decision that failed (a timeout costs its whole timeout)
    while not state.done:
        step += 1
        if not world.legal_actions(state):
            reason, stood = f"no legal placement for block {step}", False
            break
        started = time.perf_counter()
        try:
            choice = agent.choose(state, task, step, budget)
        except AgentFailed as err:
            reason, stood = str(err), False
            failed_seconds = time.perf_counter() - started
            break
        seconds = time.perf_counter() - started
        state = world.step(state, choice.action)
        stable = bool(world.is_stable(state.geometry))
        steps.append({"width": state.geometry.blocks[-1].width, "x": choice.action.x, "layer": choice.action.layer,
                      "stable": stable, "overhang": float(world.overhang(state.geometry)),
                      "calls": choice.calls, "seconds": seconds, "snapped": choice.snapped})
        if not stable:
            reason, stood = f"the tower fell at placement {step}", False
            break
    calls = [s["calls"] for s in steps]
    record = {"task_id": task.id, "sequence": list(task.sequence), "seed": int(seed), "budget": budget,
              "reward": float(world.reward(state.geometry, True)) if stood else 0.0, "stood": stood,
              "overhang": float(world.overhang(state.geometry)),
              "calls": None if not agent.counts_calls or any(c is None for c in calls) else int(sum(calls)),
              "seconds": float(sum(s["seconds"] for s in steps) + failed_seconds), "reason": reason,
              "snapped": int(sum(s["snapped"] for s in steps)), "steps": steps}
    agent.end(task, seed, record)
    return record
