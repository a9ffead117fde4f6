"""Fixtures the search-planner tests share: a static-physics world and its predictors and value."""

import pytest

from overhang_framework.plugins import Registry

REG = Registry()


@pytest.fixture(scope="module")
def world():
    return REG.create("world", {"name": "overhang", "physics": "static"})


@pytest.fixture(scope="module")
def veridical(world):
    return REG.create("predictor", {"name": "veridical"}, world=world)


@pytest.fixture(scope="module")
def ipe(world):
    return REG.create("predictor", {"name": "ipe", "K": 8}, world=world)


@pytest.fixture(scope="module")
def value(world):
    return REG.create("value", {"name": "overhang"}, world=world)
