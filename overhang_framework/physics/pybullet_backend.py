"""Reference physics: the tower in PyBullet (DIRECT mode).

Each block is a box of ``width x depth x BLOCK_HEIGHT`` with uniform density,
resting on a static ground box whose top face is ``z = 0``. The simulation
steps at ``time_step`` for ``duration`` seconds; the tower is stable when no
block's centre moved further than ``threshold`` from where it was placed.

The *reference verdict* is the full window (``early_stop=False``) on the
exact geometry. It still ends a run the moment a block has moved beyond
``threshold`` (``stop_on_fall``, checked every ``check_every`` steps): a block
that far from its place has left its support and does not come back, so the
verdict is that of the full window at a fraction of its cost for falling
towers. A tower that stands always runs the whole window.

With ``early_stop`` the run also ends when every block has been at rest (speed
below ``rest_speed``) for ``rest_time`` seconds after ``min_time``. That
"stable" is a guess, not the reference: a tower balanced exactly on an edge
rests for a while and then creeps off it (docs/physics.md).

Within about a centimetre of its tipping point the reference is chaotic: tiny
changes of the geometry can flip the verdict. ``jitters > 0`` selects a
*robust* verdict instead: the tower is stable only if it stands in the exact
geometry and in each of ``jitters`` fixed copies whose blocks are moved along
x by ``+jitter`` or ``-jitter`` (signs from a fixed seed, the same for every
tower of a given size).

The verdict is a function of the tower, not of the order its blocks are
listed in. The engine's solver visits bodies and contacts in the order they
were created, and near a tipping point that order can decide the verdict; so
every run creates the blocks in the canonical order of
:func:`~overhang_framework.geometry.canonical_order` (bottom up: by layer,
then x, then width), and a verdict cache keyed by the canonical key gives one
answer whichever order asked first. Per-block friction travels with its
block, the jitter patterns are laid on the blocks in that order, and
:meth:`PyBulletSimulator.motion` returns its frames in the listed order.
"""

from __future__ import annotations

import ctypes
import os
import sys
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import BLOCK_HEIGHT, Geometry, canonical_order
from overhang_framework.physics import check_fields


def import_pybullet():
    """The ``pybullet`` module, imported without the build-time banner its C code prints.

    The banner would land in the middle of a progress bar or of a command's
    output; standard output and error point at the null device for the import.
    """
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    try:
        with open(os.devnull, "w") as null:
            for fd in saved:
                os.dup2(null.fileno(), fd)
            import pybullet

            ctypes.CDLL(None).fflush(None)  # C's buffers, while they still point at the null device
    finally:
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
    return pybullet


@dataclass(frozen=True)
class PyBulletParams:
    time_step: float = 1.0 / 240.0
    duration: float = 5.0
    threshold: float = 0.05
    density: float = 1000.0
    depth: float = 0.6
    friction: float = 0.5
    restitution: float = 0.0
    gravity: float = 9.81
    solver_iterations: int = 50
    early_stop: bool = False
    stop_on_fall: bool = True
    check_every: int = 6
    rest_speed: float = 0.0003
    rest_time: float = 0.25
    min_time: float = 0.25
    jitters: int = 0
    jitter: float = 0.001

    def __post_init__(self):
        if isinstance(self.jitters, bool) or not isinstance(self.jitters, int) or self.jitters < 0:
            raise ValueError(f"PyBulletParams.jitters must be a whole number >= 0, got {self.jitters!r}")
        check_fields(self, positive=("time_step", "duration", "threshold", "density", "depth", "rest_speed"),
                     non_negative=("friction", "restitution", "gravity", "rest_time", "min_time", "jitter"),
                     whole=("solver_iterations", "check_every"))
        if not isinstance(self.early_stop, bool):
            raise ValueError(f"PyBulletParams.early_stop must be true or false, got {self.early_stop!r}")


@dataclass(frozen=True)
class Outcome:
    """What one check found: the verdict, the largest displacement, the steps simulated."""

    stable: bool
    displacement: float
    steps: int


def jitter_offsets(n_blocks: int, jitters: int, jitter: float) -> list[np.ndarray]:
    """The ``jitters`` fixed x offset patterns (each ``+-jitter`` per block) of the robust verdict."""
    return [jitter * np.random.default_rng([2026, n_blocks, k]).choice([-1.0, 1.0], size=n_blocks)
            for k in range(jitters)]


class PyBulletSimulator:
    """One DIRECT-mode PyBullet client, reused for many checks."""

    _listed_order = False
    """True: create the blocks in the order they are listed (the order-dependent behaviour of earlier
    versions, kept for side-by-side benchmarks only)."""

    _client: Optional[int] = None  # until connected: an interrupted construction still closes cleanly

    def __init__(self, params: PyBulletParams = PyBulletParams()):
        pybullet = import_pybullet()
        self.params = params
        self._p = pybullet
        self._client = pybullet.connect(pybullet.DIRECT)

    def close(self) -> None:
        if self._client is not None:
            try:
                self._p.disconnect(physicsClientId=self._client)
            except Exception:  # already gone with its process
                pass
            self._client = None

    def __del__(self):
        self.close()

    def _build(self, geometry: Geometry, gravity: Optional[Sequence[float]], friction):
        p, cid, prm = self._p, self._client, self.params
        p.resetSimulation(physicsClientId=cid)
        p.setPhysicsEngineParameter(
            fixedTimeStep=prm.time_step,
            numSolverIterations=prm.solver_iterations,
            physicsClientId=cid,
        )
        gx, gz = (0.0, -prm.gravity) if gravity is None else (float(gravity[0]), float(gravity[1]))
        p.setGravity(gx, 0.0, gz, physicsClientId=cid)
        ground = p.createCollisionShape(p.GEOM_BOX, halfExtents=[50, 50, 0.5], physicsClientId=cid)
        gid = p.createMultiBody(0, ground, basePosition=[0, 0, -0.5], physicsClientId=cid)
        p.changeDynamics(gid, -1, lateralFriction=prm.friction, restitution=prm.restitution,
                         physicsClientId=cid)
        bodies = []
        for i, b in enumerate(geometry.blocks):
            half = [b.width / 2, prm.depth / 2, BLOCK_HEIGHT / 2]
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
            mass = prm.density * b.width * prm.depth * BLOCK_HEIGHT
            bid = p.createMultiBody(mass, shape, basePosition=[b.x, 0.0, b.z], physicsClientId=cid)
            mu = prm.friction if friction is None else float(friction[i])
            p.changeDynamics(bid, -1, lateralFriction=mu, restitution=prm.restitution,
                             linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
            bodies.append(bid)
        return bodies

    def check(self, geometry: Geometry, gravity=None, friction=None,
              early_stop: Optional[bool] = None) -> Outcome:
        """Simulate ``geometry`` and return its :class:`Outcome`.

        ``gravity`` is an optional ``(gx, gz)`` vector (default ``(0, -g)``);
        ``friction`` an optional per-block friction coefficient. With
        ``params.jitters > 0`` the jittered copies run too (see the module
        docstring); the outcome is the first that falls, else the exact one's
        with the steps of all runs.
        """
        geometry, friction, _ = self._canonical(geometry, friction)
        outcome = self._run(geometry, gravity, friction, early_stop)
        steps = outcome.steps
        for offsets in jitter_offsets(len(geometry), self.params.jitters, self.params.jitter):
            if not outcome.stable:
                break
            moved = Geometry(tuple(type(b)(b.width, b.x + float(d), b.layer) for b, d in zip(geometry.blocks, offsets)))
            out = self._run(moved, gravity, friction, early_stop)
            steps += out.steps
            if not out.stable:
                return Outcome(False, out.displacement, steps)
        return Outcome(outcome.stable, outcome.displacement, steps)

    def _canonical(self, geometry: Geometry, friction):
        """``geometry`` with its blocks in canonical order, ``friction`` reordered alike, and the order
        (``None`` when the blocks already are in it)."""
        order = None if self._listed_order else canonical_order(geometry.blocks)
        if order is None or order == sorted(order):
            return geometry, friction, None
        blocks = geometry.blocks
        return (Geometry(tuple(blocks[i] for i in order)),
                None if friction is None else [friction[i] for i in order], order)

    def _run(self, geometry: Geometry, gravity, friction, early_stop: Optional[bool]) -> Outcome:
        p, cid, prm = self._p, self._client, self.params
        early = prm.early_stop if early_stop is None else early_stop
        watch = early or prm.stop_on_fall
        bodies = self._build(geometry, gravity, friction)
        start = np.array([[b.x, 0.0, b.z] for b in geometry.blocks]).reshape(-1, 3)
        total = int(round(prm.duration / prm.time_step))
        rest_needed = int(np.ceil(prm.rest_time / prm.time_step))
        min_steps = int(np.ceil(prm.min_time / prm.time_step))
        at_rest = 0
        step = 0
        displacement = 0.0
        while step < total:
            n = min(prm.check_every, total - step) if watch else total
            for _ in range(n):
                p.stepSimulation(physicsClientId=cid)
            step += n
            if not watch:
                break
            pos = np.array([p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in bodies])
            displacement = float(np.max(np.linalg.norm(pos - start, axis=1))) if len(bodies) else 0.0
            if displacement > prm.threshold:
                return Outcome(False, displacement, step)
            if not early:
                continue
            speed = max(
                (np.linalg.norm(v) + np.linalg.norm(w) * BLOCK_HEIGHT
                 for v, w in (p.getBaseVelocity(b, physicsClientId=cid) for b in bodies)),
                default=0.0,
            )
            at_rest = at_rest + n if speed < prm.rest_speed else 0
            if at_rest >= rest_needed and step >= min_steps:
                return Outcome(True, displacement, step)
        pos = np.array([p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in bodies])
        displacement = float(np.max(np.linalg.norm(pos - start, axis=1))) if len(bodies) else 0.0
        return Outcome(displacement <= prm.threshold, displacement, step)

    def motion(self, geometry: Geometry, fps: float = 30.0, settle: float = 0.5) -> list[list[list[float]]]:
        """The tower's motion over the window, for showing it: frames at ``fps`` of ``[x, z, angle]`` per block.

        ``angle`` is in radians, counter-clockwise in the x-z plane seen with x to the right and z up. The
        run ends at ``duration``, or once every block has rested for ``settle`` seconds after the first
        (the rest of the window would repeat the last frame). The blocks are simulated in canonical order;
        each frame lists them in ``geometry``'s order.
        """
        p, cid, prm = self._p, self._client, self.params
        geometry, _, order = self._canonical(geometry, None)
        bodies = self._build(geometry, None, None)
        if order is not None:  # body of the k-th listed block
            listed = [0] * len(order)
            for position, k in enumerate(order):
                listed[k] = bodies[position]
            bodies = listed
        total = int(round(prm.duration / prm.time_step))
        every = max(1, int(round(1.0 / (fps * prm.time_step))))
        rest_needed = max(1, int(round(settle / prm.time_step / every)))
        frames, at_rest = [], 0

        def frame():
            out = []
            for b in bodies:
                (x, _, z), quat = p.getBasePositionAndOrientation(b, physicsClientId=cid)
                out.append([round(x, 5), round(z, 5), round(-p.getEulerFromQuaternion(quat)[1], 5)])
            return out

        frames.append(frame())
        for step in range(every, total + 1, every):
            for _ in range(every):
                p.stepSimulation(physicsClientId=cid)
            frames.append(frame())
            speed = max((np.linalg.norm(v) + np.linalg.norm(w) * BLOCK_HEIGHT
                         for v, w in (p.getBaseVelocity(b, physicsClientId=cid) for b in bodies)), default=0.0)
            at_rest = at_rest + 1 if speed < 10 * prm.rest_speed else 0
            if at_rest >= rest_needed and step * prm.time_step >= 1.0:
                break
        return frames


class PyBulletBackend:
    """:class:`~overhang_framework.physics.PhysicsBackend` over one reused :class:`PyBulletSimulator`."""

    name = "pybullet"

    def __init__(self, params: PyBulletParams = PyBulletParams()):
        self.params = params
        self._sim: Optional[PyBulletSimulator] = None

    @property
    def simulator(self) -> PyBulletSimulator:
        if self._sim is None:
            self._sim = PyBulletSimulator(self.params)
        return self._sim

    def stable(self, geometry: Geometry, gravity=None, friction=None) -> bool:
        return self.simulator.check(geometry, gravity, friction).stable

    def stable_batch(self, geometries, gravity=None, friction=None) -> np.ndarray:
        return np.array(
            [
                self.stable(g, None if gravity is None else gravity[i], None if friction is None else friction[i])
                for i, g in enumerate(geometries)
            ],
            dtype=bool,
        )

    def __getstate__(self):
        return {"params": self.params, "_sim": None}
