"""Build a physics backend by name."""

from __future__ import annotations

from overhang_framework.physics.pybullet_backend import PyBulletBackend, PyBulletParams

BACKENDS = ("pybullet",)


def make_backend(name: str, **params):
    if name == "pybullet":
        return PyBulletBackend(PyBulletParams(**params))
    raise ValueError(f"unknown physics backend {name!r}; allowed: {', '.join(BACKENDS)}")
