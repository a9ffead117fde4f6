"""The environment's id, and its registration with Gymnasium (``import overhang_framework`` does it)."""

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
