"""Wrappers that give the environment the ``Box`` spaces libraries such as Stable-Baselines3 take."""

from __future__ import annotations

from typing import Any

import gymnasium as gym


class FlattenAction(gym.ActionWrapper, gym.utils.RecordConstructorArgs):
    """The ``Dict`` action as a ``Box`` in ``[-1, 1]^2``: x scaled to the grid, and the layer as equal
    bins over the layers a block can reach now (see :meth:`TowerSpaces.unflatten`)."""

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.ActionWrapper.__init__(self, env)
        self.tower_spaces = env.unwrapped.spaces
        self.action_space = self.tower_spaces.flat_action_space()

    def action(self, action: Any) -> dict:
        state = self.env.unwrapped.state
        if state is None:
            raise RuntimeError("the episode has not started; call reset() first")
        return self.tower_spaces.unflatten(action, state)


def flat_env(env_id_or_env: Any = None, **kwargs) -> gym.Env:
    """``OverhangTower-v0`` (made with ``kwargs``, or the env given) with a flat ``Box`` action and a flat
    ``Box`` observation: the form a Stable-Baselines3 ``MlpPolicy`` takes."""
    from overhang_framework.envs.registration import ENV_ID

    env = env_id_or_env if isinstance(env_id_or_env, gym.Env) else gym.make(env_id_or_env or ENV_ID, **kwargs)
    return gym.wrappers.FlattenObservation(FlattenAction(env))

