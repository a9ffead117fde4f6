"""Build a physics backend by name: ``make_backend("static", margin=0.01)``."""

from __future__ import annotations

from typing import Optional

from overhang_framework.physics.cache import CachedBackend, VerdictCache

BACKENDS = ("pybullet", "static", "tiered")
#: Backend settings that choose how a verdict is computed, not what it is (left out of a physics' identity).
SOLVER_SETTINGS = ("lp_nnls", "compiled", "nnls")


def identity(physics: str, params: dict, resolution) -> dict:
    """What verdicts under ``physics`` with ``params`` at ``resolution`` depend on: the physics, every parameter
    of its backend with the defaults filled in (less :data:`SOLVER_SETTINGS`), and the resolution."""
    import dataclasses

    try:
        params = dataclasses.asdict(backend_params(physics, **params))  # every parameter, defaults included
    except (ValueError, TypeError):
        params = dict(params)
    for name in SOLVER_SETTINGS:
        params.pop(name, None)
    return {"physics": physics, "params": params, "resolution": resolution}


def backend_params(name: str, **params):
    """The parameter dataclass of backend ``name`` with ``params`` set; ``ValueError`` for unknown
    names, unknown parameters or values out of range."""
    if name == "pybullet":
        from overhang_framework.physics.pybullet_backend import PyBulletParams as cls
    elif name == "static":
        from overhang_framework.physics.static_backend import StaticParams as cls
    elif name == "tiered":
        from overhang_framework.physics.tiered import TieredParams as cls
    else:
        raise ValueError(f"unknown physics backend {name!r}; allowed: {', '.join(BACKENDS)}")
    fields = set(cls.__dataclass_fields__)
    unknown = sorted(set(params) - fields)
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)} for physics backend {name!r}; allowed: {', '.join(sorted(fields))}"
        )
    return cls(**params)


def make_backend(name: str, *, workers: Optional[int] = None, cache=None, pybullet=None, static=None,
                 verdict_file=None, **params):
    """The backend called ``name`` with ``params`` overriding its parameter defaults.

    ``pybullet`` takes :class:`PyBulletParams` fields and, with ``workers > 1``,
    runs on a :class:`PyBulletPool`; ``static`` takes :class:`StaticParams`
    fields; ``tiered`` takes :class:`TieredParams` fields, plus the mappings
    ``pybullet`` and ``static`` for the reference and static model it is
    built on (reference checks on a pool with ``workers > 1``). ``cache`` wraps the backend in a :class:`CachedBackend`: ``True``
    for a fresh :class:`VerdictCache`, or a cache to share. ``verdict_file`` keeps the reference's
    verdicts (``pybullet``, and ``tiered``'s band) in an SQLite file for later runs. Unknown names and
    unknown parameters raise ``ValueError``.
    """
    prm = backend_params(name, **params)
    if name == "tiered":
        from overhang_framework.physics.tiered import TieredBackend

        backend = TieredBackend(prm, static=backend_params("static", **dict(static or {})),
                                pybullet=backend_params("pybullet", **dict(pybullet or {})),
                                workers=workers or 1, verdict_file=verdict_file)
    elif name == "pybullet":
        if workers is not None and workers > 1:
            from overhang_framework.physics.pool import PyBulletPool

            backend = PyBulletPool(workers=workers, params=prm)
        else:
            from overhang_framework.physics.pybullet_backend import PyBulletBackend

            backend = PyBulletBackend(prm)
        if verdict_file:
            from overhang_framework.physics.cache import DiskCachedBackend

            backend = DiskCachedBackend(backend, verdict_file)
    else:
        from overhang_framework.physics.static_backend import StaticBackend

        backend = StaticBackend(prm)
    if cache is None or cache is False:
        return backend
    return CachedBackend(backend, VerdictCache() if cache is True else cache)
