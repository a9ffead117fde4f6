"""An example plugin: a planner that picks a random legal action, with its config file.

Install it with ``pip install examples/example_plugin`` and run::

    python -m overhang_framework planner=random tasks=example
"""

from __future__ import annotations

import time

import numpy as np

from overhang_framework.hookspecs import hookimpl
from overhang_framework.interfaces import Budget, Decision, Planner, Spend


class RandomPlanner(Planner):
    """Picks uniformly among legal actions whose predicted stability is at least ``min_stability``."""

    def __init__(self, world, min_stability: float = 0.0):
        self.world = world
        if isinstance(min_stability, bool) or not isinstance(min_stability, (int, float)) \
                or not 0 <= min_stability <= 1:
            raise ValueError(f"min_stability must be a number in [0, 1], got {min_stability!r}")
        self.min_stability = float(min_stability)

    def plan(self, state, predictor, value, budget: Budget, rng: np.random.Generator) -> Decision:
        start = time.perf_counter()
        actions = self.world.legal_actions(state)
        p = np.asarray(predictor.predict(state, actions, rng), dtype=float)
        ok = np.flatnonzero(p >= self.min_stability)
        i = int(rng.choice(ok)) if len(ok) else int(np.argmax(p))
        spend = Spend(predictor_calls=1, actions_scored=len(actions), nodes_expanded=len(actions),
                      seconds=time.perf_counter() - start)
        return Decision(actions[i], float(p[i]), spend)


@hookimpl
def register_planners(register):
    register("random", RandomPlanner)


@hookimpl
def config_search_paths():
    return ["pkg://overhang_example_plugin.conf"]
