"""The ``policy`` planner: a trained agent (a saved Stable-Baselines3 policy) as an ordinary planner."""

from __future__ import annotations

import logging
import time

import numpy as np

from overhang_framework.geometry import Action
from overhang_framework.interfaces import (
    Budget,
    Decision,
    Planner,
    Predictor,
    Spend,
    State,
    Value,
    World,
)
from overhang_framework.envs.policies import policy_action
from overhang_framework.rules import legal_xs

log = logging.getLogger(__name__)


class PolicyPlanner(Planner):
    """Plays the policy saved at ``path`` by ``overhang_framework.envs.save_policy``.

    Each decision shows the policy the observation the environment would show
    (flattened as in training) and reads its flat action as the environment's
    wrapper does. ``deterministic`` plays the policy's most likely action;
    ``false`` samples it, seeded from the episode's generator. A choice the
    rules forbid is replaced by the nearest legal action at the world's
    resolution (same layer, closest x; else the closest layer), as the
    experiment's page never lets a person confirm an illegal placement;
    ``replaced`` counts them. The predictor scores the chosen action once, for
    the episode's ``predicted_stability``. Budgets and the value are not used.
    """

    def __init__(self, world: World, path: str | None = None, deterministic: bool = True):
        from overhang_framework.envs.policies import load_policy

        if not path:
            raise ValueError("planner.path must name a policy file (train one with python -m "
                             "overhang_framework.envs.ppo)")
        if not isinstance(deterministic, bool):
            raise ValueError(f"deterministic must be true or false, got {deterministic!r}")
        self.world = world
        self.path = str(path)
        self.deterministic = deterministic
        self.model, self.spaces, self.info = load_policy(path)
        self._observation_space = self.spaces.observation_space()
        self._renderer = self.spaces.renderer()
        self.replaced = 0

    def _nearest_legal(self, state: State, wanted: Action) -> Action:
        xs, layers = legal_xs(state.geometry, state.next_width, self.world.resolution)
        if not len(xs):
            raise RuntimeError("no legal action in this state")
        order = np.lexsort((np.abs(xs - wanted.x), np.abs(layers - wanted.layer)))
        k = int(order[0])
        return Action(float(xs[k]), int(layers[k]))

    def plan(self, state: State, predictor: Predictor, value: Value, budget: Budget,
             rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        if len(state.geometry) + len(state.remaining) > self.spaces.max_blocks:
            raise ValueError(f"the policy at {self.path} was trained on tasks of at most {self.spaces.max_blocks} "
                             f"blocks; this task has {len(state.geometry) + len(state.remaining)}")
        if not self.deterministic:
            import torch

            torch.manual_seed(int(rng.integers(2**63)))
        chosen = policy_action(self.model, self.spaces, self._observation_space,
                               self.spaces.observe(state, self._renderer), state, self.deterministic)
        action, _ = self.spaces.to_action(chosen)
        if action is None or self.world.illegal_reason(state, action) is not None:
            action = self._nearest_legal(state, action or Action(0.0, 1))
            self.replaced += 1
            log.info("policy chose an illegal action; playing the nearest legal one, x=%g layer=%d",
                     action.x, action.layer)
        p = float(predictor.predict(state, [action], rng)[0])
        budget.charge(1)
        spend = Spend(predictor_calls=1, actions_scored=1, seconds=time.perf_counter() - start,
                      budget_exhausted=budget.exhausted())
        return Decision(action, p, spend)
