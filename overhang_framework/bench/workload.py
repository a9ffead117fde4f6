"""The towers planners ask about: every candidate of every decision of real episodes.

:func:`planner_workload` plays tasks as ``python -m overhang_framework`` would
(one episode per task, the run's episode generators) and records, for every
decision, the tower after each candidate action the planner scored, and the
tower after each placement. The physics that drives the episodes is a choice
(``physics``); a cheap one yields the same kind of workload as the reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Sequence

from overhang_framework.geometry import Geometry


@dataclass
class Workload:
    """Candidate towers (one list per decision) and placed towers, in the order asked."""

    decisions: list[list[Geometry]] = field(default_factory=list)
    placed: list[Geometry] = field(default_factory=list)

    @property
    def candidates(self) -> list[Geometry]:
        return [g for d in self.decisions for g in d]


class _Recording:
    """A predictor that records the successors it is asked about and answers through ``inner``."""

    #: every answer goes through :meth:`predict`, so that every successor asked about is recorded
    predict_lazy = None

    def __init__(self, inner, world, workload: Workload):
        self.inner, self.world, self.workload = inner, world, workload

    def predict(self, state, actions, rng):
        self.workload.decisions.append([self.world.successor(state, a).geometry for a in actions])
        return self.inner.predict(state, actions, rng)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def planner_workload(predictor: str = "veridical", physics: str = "static", tasks: Optional[Sequence] = None,
                     seed: int = 0, world: Optional[Mapping[str, Any]] = None,
                     predictor_params: Optional[Mapping[str, Any]] = None) -> Workload:
    """The towers the myopic planner with ``predictor`` asks about on ``tasks`` (default: paper20).

    ``physics`` is the world's physics during the episodes (``world`` adds
    further world parameters); ``seed`` the run's master seed.
    """
    from overhang_framework.episode import episode_rng, run_episode
    from overhang_framework.plugins import Registry
    from overhang_framework.tasks import generate_sequences, parse_tasks

    registry = Registry()
    w = registry.create("world", {"name": "overhang", "physics": physics, **dict(world or {})})
    pred = registry.create("predictor", {"name": predictor, **dict(predictor_params or {})}, world=w)
    planner = registry.create("planner", {"name": "myopic"}, world=w)
    value = registry.create("value", {"name": "overhang"}, world=w)
    sequences = tasks if tasks is not None else generate_sequences(20, 6, 2025)
    workload = Workload()
    recording = _Recording(pred, w, workload)
    for i, task in enumerate(parse_tasks(sequences, prefix="paper")):
        record = run_episode(task, w, recording, planner, value, episode_rng(seed, i, 0))
        geometry = w.initial_state(task).geometry
        for step in record["steps"]:
            geometry = geometry.add(type(geometry.blocks[0])(step["width"], step["x"], step["layer"]))
            workload.placed.append(geometry)
    return workload
