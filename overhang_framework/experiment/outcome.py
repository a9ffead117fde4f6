"""What happens after a placement: the world's verdict, and the tower's motion for the page to show.

The verdict is the World plugin's, the same ground truth the models are scored
against (``world.physics``, the full-window PyBullet reference's verdicts by
default). The motion comes from the reference simulator over the 5 s window,
recorded at the animation's frame rate: a tower that stands is shown as placed
(its blocks move by less than the reference's threshold, a few millimetres,
which a screen does not show), and a tower that falls is simulated until its
blocks come to rest.

Each server thread keeps its own world and simulator (PyBullet clients are not
shared between threads), unless ``processes > 0``: then the verdicts are
computed in a pool of that many processes and the motions in another pool of
that many, each process with its own world (and verdict cache) and simulator.
PyBullet holds the GIL while it steps, so in the server's threads one falling
tower's motion (tens of milliseconds of stepping) or one reference run near a
tipping point stalls every other request of the process, and with a thread
each the verdict caches are rarely hit. In pools the physics runs beside the
requests, on the other cores, and a tower that stands (its verdict, mostly a
static check, well under a millisecond) never waits behind another's motion.
The verdicts and the frames are the same either way.
"""

from __future__ import annotations

import threading
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Mapping

from overhang_framework.geometry import Geometry


@dataclass(frozen=True)
class Outcome:
    stable: bool
    poses: list  # frames of [x, z, angle] per block


class Outcomes:
    """Verdicts and motions under the world ``world_config`` describes (a resolved ``world`` config)."""

    def __init__(self, world_config: Mapping[str, Any], fps: float = 30.0, processes: int = 0):
        if isinstance(processes, bool) or not isinstance(processes, int) or processes < 0:
            raise ValueError(f"processes must be a whole number >= 0, got {processes!r}")
        self.world_config = dict(world_config)
        self.fps = float(fps)
        self.processes = processes
        self._local = threading.local()
        self._pools: dict[str, ProcessPoolExecutor] = {}
        self._pools_lock = threading.Lock()

    def world(self):
        world = getattr(self._local, "world", None)
        if world is None:
            from overhang_framework.plugins import Registry

            world = self._local.world = Registry().create("world", self.world_config)
        return world

    def _simulator(self):
        sim = getattr(self._local, "sim", None)
        if sim is None:
            from overhang_framework.physics.factory import backend_params
            from overhang_framework.physics.pybullet_backend import PyBulletSimulator

            params = backend_params("pybullet", **dict(self.world_config.get("pybullet") or {}))
            sim = self._local.sim = PyBulletSimulator(params)
        return sim

    def __call__(self, geometry: Geometry) -> Outcome:
        if self.processes:
            stable = self._pool("verdicts").submit(_verdict, self.world_config, self.fps, geometry).result()
            if stable:
                return Outcome(True, _as_placed(geometry))
            return Outcome(False, self._pool("motions").submit(_motion, self.world_config, self.fps, geometry).result())
        return self.compute(geometry)

    def compute(self, geometry: Geometry) -> Outcome:
        """The outcome, computed in this thread."""
        if self.world().is_stable(geometry):
            return Outcome(True, _as_placed(geometry))
        return Outcome(False, self._simulator().motion(geometry, fps=self.fps))

    def _pool(self, name: str) -> ProcessPoolExecutor:
        with self._pools_lock:
            pool = self._pools.get(name)
            if pool is None:
                import multiprocessing

                # spawn, not fork: the server's threads, locks and PyBullet clients stay out of the workers
                pool = self._pools[name] = ProcessPoolExecutor(
                    self.processes, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_warm, initargs=(self.world_config, self.fps, name))
            return pool

    def start(self) -> None:
        """Start the pools now, with the world and PyBullet loaded in each process, rather than on first use."""
        if self.processes:
            futures = [self._pool(name).submit(_ready) for name in ("verdicts", "motions") for _ in range(self.processes)]
            for f in futures:
                f.result()

    def close(self) -> None:
        """Stop the pools (when there are any)."""
        with self._pools_lock:
            pools, self._pools = list(self._pools.values()), {}
        for pool in pools:
            pool.shutdown(wait=True, cancel_futures=True)


def _as_placed(geometry: Geometry) -> list:
    return [[[b.x, b.z, 0.0] for b in geometry.blocks]]


# In a pool's process: one Outcomes per world, computing in the process's only thread.
_OUTCOMES: dict = {}


def _outcomes(world_config: Mapping[str, Any], fps: float) -> Outcomes:
    key = (repr(sorted(world_config.items())), fps)
    if key not in _OUTCOMES:
        _OUTCOMES[key] = Outcomes(world_config, fps)
    return _OUTCOMES[key]


def _warm(world_config: Mapping[str, Any], fps: float, role: str) -> None:
    outcomes = _outcomes(world_config, fps)
    outcomes.world() if role == "verdicts" else outcomes._simulator()


def _ready() -> bool:
    return True


def _verdict(world_config: Mapping[str, Any], fps: float, geometry: Geometry) -> bool:
    return bool(_outcomes(world_config, fps).world().is_stable(geometry))


def _motion(world_config: Mapping[str, Any], fps: float, geometry: Geometry) -> list:
    return _outcomes(world_config, fps)._simulator().motion(geometry, fps=fps)
