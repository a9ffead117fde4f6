"""Leaf values for search: the leaf's overhang, and a greedy rollout to the end of the episode."""

from __future__ import annotations

from typing import Optional

import numpy as np

from overhang_framework.geometry import overhang
from overhang_framework.interfaces import State, Value, World
from overhang_framework.search import reach_bound, state_key


class OverhangValue(Value):
    """The overhang of the leaf's geometry (the paper's ``V(s_{t+D})``)."""

    #: Its values are overhangs of geometries on the world's grid (see ``search.lattice_step``).
    lattice = True

    def __init__(self, world: Optional[World] = None):
        self.world = world

    def __call__(self, state: State) -> float:
        return overhang(state.geometry)

    def children_values(self, expansion) -> np.ndarray:
        """The values of an expansion's children at once (their overhang, already computed)."""
        return expansion.overhang

    def bound(self, state: State, depth: int) -> Optional[float]:
        if self.world is None:
            return None
        return reach_bound(self.world, state, depth)


class RolloutValue(Value):
    """The reward a greedy continuation earns from the leaf to the end of the episode.

    From the leaf, each remaining block is placed where it gives the most
    overhang among the placements that ``physics`` calls stable (``static``:
    the static-equilibrium backend with the world's parameters, cheap; ``world``:
    the world's own physics). The value is the final overhang, or 0 when some
    block has no stable placement. It sees past the search horizon at the cost
    of one batched physics check per remaining block; results are memoised by
    state.
    """

    PHYSICS = ("static", "world")

    def __init__(self, world: World, physics: str = "static", resolution: Optional[float] = None):
        if physics not in self.PHYSICS:
            raise ValueError(f"unknown rollout physics {physics!r}; allowed: {', '.join(self.PHYSICS)}")
        if resolution is not None and (isinstance(resolution, bool) or not isinstance(resolution, (int, float))
                                       or resolution <= 0):
            raise ValueError(f"resolution must be a positive number of metres or null, got {resolution!r}")
        self.world = world
        self.physics = physics
        self.resolution = resolution
        self._backend = None
        self._memo: dict = {}

    @property
    def backend(self):
        if self._backend is None:
            if self.physics == "world":
                self._backend = getattr(self.world, "backend", None) or _WorldVerdicts(self.world)
            else:
                from overhang_framework.physics.factory import make_backend

                params = dict(getattr(self.world, "backend_params", {}).get("static", {}))
                self._backend = make_backend("static", cache=True, **params)
        return self._backend

    def __call__(self, state: State) -> float:
        key = state_key(state)
        if key in self._memo:
            return self._memo[key]
        current = state
        value = overhang(state.geometry)
        while not current.done:
            actions = self.world.legal_actions(current, self.resolution)
            children = [self.world.successor(current, a) for a in actions]
            stable = np.asarray(self.backend.stable_batch([c.geometry for c in children]), dtype=bool) \
                if children else np.zeros(0, dtype=bool)
            if not stable.any():
                value = 0.0
                break
            reach = np.array([overhang(c.geometry) for c in children])
            reach[~stable] = -np.inf
            current = children[int(np.argmax(reach))]
            value = overhang(current.geometry)
        self._memo[key] = float(value)
        return float(value)

    def bound(self, state: State, depth: int) -> Optional[float]:
        return reach_bound(self.world, state, len(state.remaining))


class _WorldVerdicts:
    """A world's own ``is_stable``, in the batched form the rollout asks for."""

    def __init__(self, world: World):
        self.world = world

    def stable_batch(self, geometries) -> np.ndarray:
        return np.array([self.world.is_stable(g) for g in geometries], dtype=bool)
