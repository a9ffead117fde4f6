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
