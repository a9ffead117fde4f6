"""Reference verdicts at the cost of static checks: decide with the cheapest stage that is sure.

The reference verdict is the full-window PyBullet run of the exact geometry
(:mod:`~overhang_framework.physics.pybullet_backend`, ``early_stop=False``).
The static backend answers in microseconds but is a different model; near the
tipping point the two disagree. :class:`TieredBackend` therefore asks the
static model twice, at two settings that bracket the reference:

* **stands for sure**: static equilibrium with every contact shrunk by
  ``stable_margin`` at both ends, under gravity tilted by ``+stable_tilt``
  and by ``-stable_tilt`` (the tilt moves a load's line of action by its
  height above the contact times the tilt, so the band grows with the
  tower's height, as the engine's compliance does), and, with
  ``frictionless_stable``, also with every friction coefficient 0 and
  gravity as given (a tower that needs friction to stand, a friction jam,
  is never taken on the static model's word). Only interpenetration-free
  towers qualify.
* **falls for sure**: no static equilibrium even with block friction
  ``fall_friction``, blocks of one layer up to ``fall_side_gap`` apart
  counted as touching (a tipping block may come to rest against a
  neighbour), under gravity as given and tilted by ``+fall_tilt`` and
  ``-fall_tilt``, with every contact shrunk by ``fall_margin`` (a negative
  value widens them). With the default 0, a load passing exactly through a
  support's edge is not a sure fall: in the reference most such towers rest
  for a while, then creep off the edge and fall, but not all
  (docs/physics.md), so they go to the reference.

A tower that is neither (the band around its tipping point) goes to the
reference: the full-window PyBullet run, which ends early only once a block
has passed the displacement threshold (falling is final). With ``workers > 1``
those runs go to a process pool.

Both settings are calibrated against the full window on generated
near-critical families and on every tower planners ask about
(``python -m overhang_framework.bench.agreement``; docs/physics.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import Geometry
from overhang_framework.physics import check_fields
from overhang_framework.physics.pybullet_backend import PyBulletParams
from overhang_framework.physics.static_backend import StaticBackend, StaticParams

STAGES = ("static_stable", "static_fall", "reference")


@dataclass(frozen=True)
class TieredParams:
    """Settings of the two static stages of :class:`TieredBackend` (units: metres, radians)."""

    stable_margin: float = 0.005
    stable_tilt: float = 0.04
    frictionless_stable: bool = True
    fall_margin: float = 0.0
    fall_tilt: float = 0.0
    fall_friction: float = 0.6
    fall_side_gap: float = 0.12

    def __post_init__(self):
        check_fields(self, non_negative=("stable_margin", "stable_tilt", "fall_tilt",
                                         "fall_friction", "fall_side_gap"))
        if isinstance(self.fall_margin, bool) or not isinstance(self.fall_margin, (int, float)) \
                or not np.isfinite(self.fall_margin) or self.fall_margin > self.stable_margin:
            raise ValueError(f"TieredParams.fall_margin must be a number <= stable_margin, got {self.fall_margin!r}")
        if not isinstance(self.frictionless_stable, bool):
            raise ValueError(f"TieredParams.frictionless_stable must be true or false, got {self.frictionless_stable!r}")
        for name in ("stable_tilt", "fall_tilt"):
            if getattr(self, name) >= np.pi / 4:
                raise ValueError(f"TieredParams.{name} must be below pi/4 rad, got {getattr(self, name)!r}")


def _tilted(gravity: np.ndarray, angle: float) -> np.ndarray:
    """Every row ``(gx, gz)`` of ``gravity`` turned by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.c_[c * gravity[:, 0] - s * gravity[:, 1], s * gravity[:, 0] + c * gravity[:, 1]]


class TieredBackend:
    """:class:`~overhang_framework.physics.PhysicsBackend` giving the full-window reference's verdicts.

    ``params`` set the static stages (:class:`TieredParams`), ``static`` the
    static model they start from (friction, ground friction, gravity, side
    contacts; its ``margin``, ``height_margin`` and ``friction_scale`` are
    replaced by the stages' own settings),
    ``pybullet`` the reference (its ``early_stop`` is ignored: the reference is
    the full window). ``workers > 1`` runs reference checks on a
    :class:`~overhang_framework.physics.pool.PyBulletPool`. ``counts`` holds how
    many geometries each stage decided.
    """

    name = "tiered"

    def __init__(self, params: TieredParams = TieredParams(), static: StaticParams = StaticParams(),
                 pybullet: PyBulletParams = PyBulletParams(), workers: int = 1, verdict_file=None):
        self.tiers = params
        self.static_params = static
        self.reference_params = replace(pybullet, early_stop=False)
        self.workers = max(1, int(workers))
        self.verdict_file = verdict_file
        self.params = (params, static, self.reference_params)
        self.counts = dict.fromkeys(STAGES, 0)
        static = replace(static, height_margin=0.0, friction_scale=1.0)  # the stages bring their own margins
        base = replace(static, side_overlap=1e-6)
        self._stable = StaticBackend(replace(base, margin=params.stable_margin))
        self._fall = StaticBackend(replace(static, margin=params.fall_margin, side_gap=params.fall_side_gap,
                                           side_overlap=1e9, friction=params.fall_friction))
        self._reference = None

    @property
    def reference(self):
        """The full-window PyBullet backend (or pool) that decides the band."""
        if self._reference is None:
            if self.workers > 1:
                from overhang_framework.physics.pool import PyBulletPool

                self._reference = PyBulletPool(self.workers, params=self.reference_params, early_stop=False)
            else:
                from overhang_framework.physics.pybullet_backend import PyBulletBackend

                self._reference = PyBulletBackend(self.reference_params)
            if self.verdict_file:
                from overhang_framework.physics.cache import DiskCachedBackend

                # keyed by the reference's own parameters: the file serves any world with the same reference
                self._reference = DiskCachedBackend(self._reference, self.verdict_file)
        return self._reference

    def _arrays(self, geometries: Sequence[Geometry], gravity, friction):
        """The geometries as padded arrays ``(W, X, L)`` (a width of 0 pads a shorter tower), gravity per row
        and friction per block (or ``None``), built once for every stage."""
        n = len(geometries)
        sp = self.static_params
        g = np.tile([0.0, -sp.gravity], (n, 1)) if gravity is None else np.asarray(gravity, dtype=float).reshape(n, 2)
        from overhang_framework.render import block_arrays

        W, X, L, _ = block_arrays(geometries)
        fric = None if friction is None else np.zeros((n, W.shape[1]))
        if fric is not None:
            for i, geo in enumerate(geometries):
                fric[i, :len(geo)] = np.asarray(friction[i], dtype=float)[:len(geo)]
        return W, X, L, g, fric

    def _sure(self, W, X, L, g, fric, tilt) -> np.ndarray:
        """The "stands for sure" check on arrays; ``tilt`` one angle or one per row."""
        n = W.shape[0]
        tilt = np.broadcast_to(np.asarray(tilt, dtype=float), (n,))
        rows = np.arange(n)
        sure = np.ones(n, dtype=bool)
        settings = [(_tilted(g, tilt), fric), (_tilted(g, -tilt), fric)]
        if self.tiers.frictionless_stable:
            settings.append((g, np.zeros(W.shape)))
        for grav, fr in settings:
            rows = rows[sure[rows]]
            if not rows.size:
                break
            sure[rows] = self._stable.stable_arrays(W[rows], X[rows], L[rows], grav[rows],
                                                    None if fr is None else fr[rows])
        return sure

    def stands_for_sure(self, geometries: Sequence[Geometry], tilt=None, gravity=None, friction=None) -> np.ndarray:
        """Per geometry, whether the "stands for sure" stage passes with gravity tilted by ``tilt`` (one angle
        or one per geometry; default ``stable_tilt``) instead of ``stable_tilt``, its other settings unchanged."""
        geometries = list(geometries)
        if not geometries:
            return np.zeros(0, dtype=bool)
        W, X, L, g, fric = self._arrays(geometries, gravity, friction)
        return self._sure(W, X, L, g, fric, self.tiers.stable_tilt if tilt is None else tilt)

    def classify(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> np.ndarray:
        """Per geometry, what the static stages say: 1 stands for sure, 0 falls for sure, -1 unsure."""
        geometries = list(geometries)
        n = len(geometries)
        out = np.full(n, -1, dtype=np.int8)
        if n == 0:
            return out
        sp = self.static_params
        W, X, L, g, fric = self._arrays(geometries, gravity, friction)

        def ask(backend, rows, grav, fr):
            return backend.stable_arrays(W[rows], X[rows], L[rows], grav[rows], None if fr is None else fr[rows])

        t = self.tiers
        sure = self._sure(W, X, L, g, fric, t.stable_tilt)
        out[sure] = 1
        fric_fall = None if fric is None else fric * (t.fall_friction / sp.friction if sp.friction > 0 else 1.0)
        rows = np.flatnonzero(~sure)
        falls = np.zeros(n, dtype=bool)
        falls[rows] = True
        tilts = (0.0, t.fall_tilt, -t.fall_tilt) if t.fall_tilt > 0 else (0.0,)
        for angle in tilts:
            rows = rows[falls[rows]]
            if not rows.size:
                break
            falls[rows] = ~ask(self._fall, rows, _tilted(g, angle), fric_fall)
        out[falls & ~sure] = 0
        return out

    def stable_batch(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> np.ndarray:
        geometries = list(geometries)
        stage = self.classify(geometries, gravity, friction)
        out = stage == 1
        unsure = np.flatnonzero(stage < 0)
        if unsure.size:
            out[unsure] = self.reference.stable_batch(
                [geometries[i] for i in unsure],
                None if gravity is None else np.asarray(gravity, dtype=float).reshape(-1, 2)[unsure],
                None if friction is None else [friction[i] for i in unsure],
            )
        self.counts["static_stable"] += int(np.sum(stage == 1))
        self.counts["static_fall"] += int(np.sum(stage == 0))
        self.counts["reference"] += int(unsure.size)
        return out

    def stable(self, geometry: Geometry, gravity=None, friction=None) -> bool:
        return bool(self.stable_batch([geometry], None if gravity is None else [gravity],
                                      None if friction is None else [friction])[0])

    def stats(self) -> dict:
        """How many geometries each stage decided (``static_stable``, ``static_fall``, ``reference``)."""
        return dict(self.counts)

    def close(self) -> None:
        close = getattr(self._reference, "close", None)
        if close is not None:
            close()

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_reference"] = None
        return state
