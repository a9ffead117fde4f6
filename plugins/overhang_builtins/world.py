"""The Overhang Tower world of the paper: grid rules, PyBullet (or static) physics, overhang reward."""

from __future__ import annotations

from typing import Any, Mapping, Optional

from overhang_framework.errors import IllegalActionError
from overhang_framework.geometry import Action, Block, Geometry, check_width, overhang
from overhang_framework.interfaces import State, Task, World
from overhang_framework import rules


class OverhangWorld(World):
    """Blocks of height 0.6 on an 8 x 8 grid; the first block stands at the ground centre.

    ``physics`` names the ground-truth backend (``pybullet`` or ``static``), whose
    parameters are the mapping of the same name; ``resolution`` is the x step of
    the candidate actions that :meth:`legal_actions` enumerates; ``cache``
    memoises verdicts by the canonical geometry key; ``workers > 1`` runs
    PyBullet batches on a process pool of that many workers.
    """

    def __init__(self, physics: str = "pybullet", resolution: float = 0.1, cache: bool = True,
                 workers: int = 1, **backend_params: Mapping[str, Any]):
        from overhang_framework.physics.factory import make_backend

        if resolution <= 0:
            raise ValueError(f"world.resolution must be positive, got {resolution}")
        self.resolution = float(resolution)
        self.physics_name = physics
        self.backend_params = {k: dict(v) for k, v in backend_params.items()}
        self.backend = make_backend(physics, workers=workers, cache=bool(cache),
                                    **self.backend_params.get(physics, {}))

    def initial_state(self, task: Task) -> State:
        widths = tuple(check_width(w) for w in task.sequence)
        if not widths:
            raise ValueError(f"task {task.id!r} has no blocks")
        return State(Geometry((Block(widths[0], 0.0, 0),)), widths[1:])

    def legal_actions(self, state: State, resolution: Optional[float] = None) -> list[Action]:
        if state.done:
            return []
        return rules.legal_actions(state.geometry, state.next_width, resolution or self.resolution)

    def illegal_reason(self, state: State, action: Action) -> Optional[str]:
        if state.done:
            return "no block is left to place"
        return rules.illegal_reason(state.geometry, state.next_width, action)

    def step(self, state: State, action: Action) -> State:
        reason = self.illegal_reason(state, action)
        if reason is not None:
            raise IllegalActionError(f"illegal action (x={action.x:g}, layer={action.layer}): {reason}")
        return State(rules.place(state.geometry, state.next_width, action), state.remaining[1:])

    def is_stable(self, geometry: Geometry) -> bool:
        return bool(self.backend.stable(geometry))

    def is_stable_batch(self, geometries):
        return self.backend.stable_batch(list(geometries))

    def overhang(self, geometry: Geometry) -> float:
        return overhang(geometry)
