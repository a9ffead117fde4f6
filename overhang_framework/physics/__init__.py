"""Physics backends: decide whether a tower stands.

A backend answers for one geometry (:meth:`PhysicsBackend.stable`) or for many
at once (:meth:`PhysicsBackend.stable_batch`). Both accept the perturbations an
intuitive physics engine applies: block x positions are whatever the geometry
says (they may leave small gaps or overlaps), an optional gravity vector
``(gx, gz)`` per geometry, and an optional friction coefficient per block.
"""

from __future__ import annotations

from typing import Optional, Protocol, Sequence, runtime_checkable

import numpy as np

from overhang_framework.geometry import Geometry


@runtime_checkable
class PhysicsBackend(Protocol):
    name: str

    def stable(self, geometry: Geometry, gravity: Optional[Sequence[float]] = None,
               friction: Optional[Sequence[float]] = None) -> bool:
        """Whether ``geometry`` stands under ``gravity`` (``(gx, gz)``) with per-block ``friction``."""

    def stable_batch(self, geometries: Sequence[Geometry], gravity: Optional[np.ndarray] = None,
                     friction: Optional[Sequence[Sequence[float]]] = None) -> np.ndarray:
        """Boolean array, one verdict per geometry; ``gravity`` is ``(n, 2)``, ``friction`` one row per geometry."""


def check_fields(params, positive: Sequence[str] = (), non_negative: Sequence[str] = (),
                 whole: Sequence[str] = ()) -> None:
    """Raise ``ValueError`` naming the first field of ``params`` outside its allowed range.

    ``positive`` fields must be numbers > 0, ``non_negative`` numbers >= 0 and
    ``whole`` whole numbers >= 1.
    """
    kind = type(params).__name__
    for names, ok, allowed in (
        (positive, lambda v: v > 0, "a number > 0"),
        (non_negative, lambda v: v >= 0, "a number >= 0"),
        (whole, lambda v: float(v).is_integer() and v >= 1, "a whole number >= 1"),
    ):
        for name in names:
            value = getattr(params, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
                    or not ok(value):
                raise ValueError(f"{kind}.{name} must be {allowed}, got {value!r}")
