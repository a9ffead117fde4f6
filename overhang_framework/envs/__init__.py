"""Gymnasium environments of the Overhang Tower task.

Importing :mod:`overhang_framework` registers ``overhang_framework/OverhangTower-v0``::

    import gymnasium as gym
    import overhang_framework

    env = gym.make("overhang_framework/OverhangTower-v0", tasks="paper20", physics="static")

:class:`FlattenAction` (or :func:`flat_env`) gives the ``Box`` action and
observation that Stable-Baselines3 takes. See docs/rl.md.
"""

from __future__ import annotations

from overhang_framework.envs.registration import ENV_ID, register  # noqa: F401


def __getattr__(name):
    if name == "OverhangTowerEnv":
        from overhang_framework.envs.tower import OverhangTowerEnv

        return OverhangTowerEnv
    if name in ("FlattenAction", "flat_env"):
        from overhang_framework.envs import wrappers

        return getattr(wrappers, name)
    raise AttributeError(name)
