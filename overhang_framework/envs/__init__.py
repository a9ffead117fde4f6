"""Gymnasium environments of the Overhang Tower task.

Importing :mod:`overhang_framework` registers ``overhang_framework/OverhangTower-v0``::

    import gymnasium as gym
    import overhang_framework

    env = gym.make("overhang_framework/OverhangTower-v0", tasks="paper20", physics="static")

:class:`FlattenAction` (or :func:`flat_env`) gives the ``Box`` action and
observation that Stable-Baselines3 takes. See docs/rl.md.
"""

from __future__ import annotations

ENV_ID = "overhang_framework/OverhangTower-v0"


def register() -> None:
    """Register :data:`ENV_ID` with Gymnasium (once; nothing when Gymnasium is not installed)."""
    try:
        import gymnasium
    except ImportError:
        return
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="overhang_framework.envs.tower:OverhangTowerEnv")


def __getattr__(name):
    if name == "OverhangTowerEnv":
        from overhang_framework.envs.tower import OverhangTowerEnv

        return OverhangTowerEnv
    if name in ("FlattenAction", "flat_env"):
        from overhang_framework.envs import wrappers

        return getattr(wrappers, name)
    raise AttributeError(name)
