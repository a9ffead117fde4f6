"""The built-in plugins honour the interface contracts."""

import pytest

from overhang_framework.plugins import Registry
from overhang_framework.testing.contracts import (
    PlannerContract, PredictorContract, ValueContract, WorldContract,
)


class TestOverhangWorld(WorldContract):
    pass


class TestVeridicalPredictor(PredictorContract):
    @pytest.fixture
    def predictor(self, world):
        return Registry().create("predictor", {"name": "veridical"}, world=world)


class TestMyopicPlanner(PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "myopic"}, world=world)


class TestOverhangValue(ValueContract):
    @pytest.fixture
    def value(self, world):
        return Registry().create("value", {"name": "overhang"}, world=world)


class _StaticWorld:
    """Search planners and rollouts check thousands of towers: the static physics keeps these quick."""

    @pytest.fixture
    def world(self):
        return Registry().create("world", {"name": "overhang", "physics": "static"})


class TestLookaheadPlanner(_StaticWorld, PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "lookahead", "depth": 2}, world=world)


class TestSoftmaxLookaheadPlanner(_StaticWorld, PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "lookahead", "depth": 2, "choice": "softmax", "beta": 5.0},
                                 world=world)


class TestOptimalPlanner(_StaticWorld, PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "optimal"}, world=world)


class TestRolloutValue(_StaticWorld, ValueContract):
    @pytest.fixture
    def value(self, world):
        return Registry().create("value", {"name": "rollout"}, world=world)


class TestHandPredictor(_StaticWorld, PredictorContract):
    @pytest.fixture
    def predictor(self, world):
        return Registry().create("predictor", {"name": "hand", "inner": "ipe", "inner_params": {"K": 8},
                                               "sd": 0.03}, world=world)


class TestRiskAverseLookaheadPlanner(_StaticWorld, PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "lookahead", "depth": 2, "risk": 0.5}, world=world)


class TestEdgePlanner(_StaticWorld, PlannerContract):
    @pytest.fixture
    def planner(self, world):
        return Registry().create("planner", {"name": "edge", "choice": "softmax", "beta": 20.0}, world=world)
