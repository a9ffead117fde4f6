"""What happens after a placement: the world's verdict, and the tower's motion for the page to show.

The verdict is the World plugin's, the same ground truth the models are scored
against (``world.physics``, the full-window PyBullet reference's verdicts by
default). The motion comes from the reference simulator over the 5 s window,
recorded at the animation's frame rate: a tower that stands is shown as placed
(its blocks move by less than the reference's threshold, a few millimetres,
which a screen does not show), and a tower that falls is simulated until its
blocks come to rest.

Each server thread keeps its own world and simulator (PyBullet clients are not
shared between threads).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Mapping

from overhang_framework.geometry import Geometry


@dataclass(frozen=True)
class Outcome:
    stable: bool
    poses: list  # frames of [x, z, angle] per block


class Outcomes:
    """Verdicts and motions under the world ``world_config`` describes (a resolved ``world`` config)."""

    def __init__(self, world_config: Mapping[str, Any], fps: float = 30.0):
        self.world_config = dict(world_config)
        self.fps = float(fps)
        self._local = threading.local()

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
        stable = self.world().is_stable(geometry)
        if stable:
            return Outcome(True, [[[b.x, b.z, 0.0] for b in geometry.blocks]])
        return Outcome(False, self._simulator().motion(geometry, fps=self.fps))
