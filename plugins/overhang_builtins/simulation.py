"""Simulation-based predictors."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from overhang_framework import rules
from overhang_framework.geometry import Action
from overhang_framework.interfaces import Predictor, State, World


class VeridicalPredictor(Predictor):
    """Noise-free physics: 1 where the world's physics says the tower stands, else 0."""

    def __init__(self, world: World):
        self.world = world

    def predict(self, state: State, actions: Sequence[Action], rng: np.random.Generator) -> np.ndarray:
        successors = [rules.place(state.geometry, state.next_width, a) for a in actions]
        return self.world.is_stable_batch(successors).astype(float)
