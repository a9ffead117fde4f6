"""The Overhang Tower world of the paper: grid rules, physics with the reference's verdicts, overhang reward."""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from overhang_framework import rules
from overhang_framework.geometry import Action, Block, Geometry, check_width, overhang
from overhang_framework.interfaces import State, Task, World


class OverhangWorld(World):
    """Blocks of height 0.6 on an 8 x 8 grid; the first block stands at the ground centre.

    ``physics`` names the ground-truth backend: ``tiered`` (the full-window
    PyBullet reference's verdicts, decided by static checks where they are
    sure), ``pybullet`` (the reference itself with ``early_stop: false``) or
    ``static`` (static equilibrium); ``tiered``, ``pybullet`` and ``static``
    are the parameters of each backend (see ``conf/world/overhang.yaml``;
    ``tiered`` builds on the other two). ``resolution`` is the x step of the candidate
    actions that :meth:`legal_actions` enumerates; ``cache`` memoises verdicts by
    the canonical geometry key; ``workers > 1`` runs PyBullet batches on a
    process pool of that many workers. ``verdict_file`` keeps the full-window reference's verdicts in an
    SQLite file that later runs, and the jobs of a sweep, reuse.
    """

    def __init__(self, physics: str = "tiered", resolution: float = 0.1, cache: bool = True,
                 workers: int = 1, pybullet: Optional[Mapping[str, Any]] = None,
                 static: Optional[Mapping[str, Any]] = None, tiered: Optional[Mapping[str, Any]] = None,
                 verdict_file: Optional[str] = None):
        from overhang_framework.physics.factory import backend_params, make_backend

        if not isinstance(resolution, (int, float)) or isinstance(resolution, bool) or resolution <= 0:
            raise ValueError(f"resolution must be a positive number of metres, got {resolution!r}")
        if not isinstance(cache, bool):
            raise ValueError(f"cache must be true or false, got {cache!r}")
        if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.resolution = float(resolution)
        self.workers = workers
        self.physics_name = physics
        for name, given in (("pybullet", pybullet), ("static", static), ("tiered", tiered)):
            if given is not None and not isinstance(given, Mapping):
                raise ValueError(f"{name} must be a mapping of {name} parameters, got {given!r}")
        self.backend_params = {"pybullet": dict(pybullet or {}), "static": dict(static or {}),
                               "tiered": dict(tiered or {})}
        if physics not in self.backend_params:
            raise ValueError(f"unknown physics {physics!r}; allowed: {', '.join(self.backend_params)}")
        for name, params in self.backend_params.items():
            backend_params(name, **params)
        extra = {"pybullet": self.backend_params["pybullet"], "static": self.backend_params["static"]} \
            if physics == "tiered" else {}
        if verdict_file is not None and not isinstance(verdict_file, str):
            raise ValueError(f"verdict_file must be a file path or null, got {verdict_file!r}")
        self.verdict_file = verdict_file
        self.backend = make_backend(physics, workers=workers, cache=cache, verdict_file=verdict_file,
                                    **self.backend_params[physics], **extra)

    def initial_state(self, task: Task) -> State:
        widths = tuple(check_width(w) for w in task.sequence)
        if not widths:
            raise ValueError(f"task {task.id!r} has no blocks")
        return State(Geometry((Block(widths[0], 0.0, 0),)), widths[1:])

    def legal_actions(self, state: State, resolution: Optional[float] = None) -> list[Action]:
        if state.done:
            return []
        return rules.legal_actions(state.geometry, state.next_width, resolution or self.resolution)

    def legal_xs(self, state: State, resolution: Optional[float] = None):
        """:meth:`legal_actions` as arrays ``(xs, layers)``, in the same order (searches that only need
        the numbers skip making an action object each)."""
        if state.done:
            return np.zeros(0), np.zeros(0, dtype=int)
        return rules.legal_xs(state.geometry, state.next_width, resolution or self.resolution)

    def illegal_reason(self, state: State, action: Action) -> Optional[str]:
        if state.done:
            return "no block is left to place"
        return rules.illegal_reason(state.geometry, state.next_width, action)

    def successor(self, state: State, action: Action) -> State:
        if state.done:
            raise ValueError("no block is left to place")
        return State(rules.place(state.geometry, state.next_width, action), state.remaining[1:])

    def is_stable(self, geometry: Geometry) -> bool:
        return bool(self.backend.stable(geometry))

    @property
    def deferred_verdicts(self) -> bool:
        """Whether some verdicts cost a reference run that a search may put off (the tiered physics)."""
        return self.physics_name == "tiered"

    def stable_batch(self, geometries) -> "np.ndarray":
        """:meth:`is_stable` of many geometries in one physics call (reference runs on the pool with workers > 1)."""
        return np.asarray(self.backend.stable_batch(list(geometries)), dtype=bool)

    def settle(self, geometries) -> "np.ndarray":
        """The verdicts of geometries that :meth:`stability_bounds` left unsure (-1): the reference runs
        them (on the pool with workers > 1), and they are cached; counted once, as its misses were."""
        from overhang_framework.physics.cache import CachedBackend, verdict_key

        geometries = list(geometries)
        backend = self.backend
        if not isinstance(backend, CachedBackend):
            return self.stable_batch(geometries)
        verdicts = np.asarray(backend.backend.stable_batch(geometries), dtype=bool)
        for g, v in zip(geometries, verdicts):
            backend.cache.put(verdict_key(g, None, None, backend._context), bool(v))
        return verdicts

    def stability_bounds(self, geometries) -> "np.ndarray":
        """What is known about each geometry's verdict without running the reference: 1 stands, 0 falls,
        -1 only the full-window reference can tell (the tiered physics' band near a tipping point).

        Cached verdicts are used; the static stages' sure verdicts are cached. Physics without stages
        (``pybullet``, ``static``) answer every geometry.
        """
        from overhang_framework.physics.cache import CachedBackend, verdict_key

        geometries = list(geometries)
        backend = self.backend
        inner = backend.backend if isinstance(backend, CachedBackend) else backend
        if not hasattr(inner, "classify"):
            return np.asarray(backend.stable_batch(geometries), dtype=np.int8)
        out = np.full(len(geometries), -1, dtype=np.int8)
        todo, keys = [], []
        for i, g in enumerate(geometries):
            if isinstance(backend, CachedBackend):
                key = verdict_key(g, None, None, backend._context)
                verdict = backend.cache.get(key)  # counted: a miss is a verdict this world computes
                if verdict is not None:
                    out[i] = verdict
                    continue
                keys.append(key)
            todo.append(i)
        if todo:
            stage = inner.classify([geometries[i] for i in todo])
            out[todo] = stage
            counts = getattr(inner, "counts", None)
            if counts is not None:
                counts["static_stable"] += int(np.sum(stage == 1))
                counts["static_fall"] += int(np.sum(stage == 0))
            if isinstance(backend, CachedBackend):
                for key, s in zip(keys, stage):
                    if s >= 0:
                        backend.cache.put(key, bool(s))
        return out

    def overhang(self, geometry: Geometry) -> float:
        return overhang(geometry)

    def stats(self) -> dict:
        stats = getattr(self.backend, "stats", None)
        return {"physics": self.physics_name, "cache": stats()} if stats else {"physics": self.physics_name}
