"""A third-party plugin adding one of each kind, with its own config directory, proved by the contract suites."""

import numpy as np
import pytest

from overhang_framework.config import compose_config
from overhang_framework.geometry import Action
from overhang_framework.hookspecs import hookimpl
from overhang_framework.interfaces import Predictor, Value
from overhang_framework.plugins import Registry
from overhang_framework.testing.contracts import (
    PlannerContract, PredictorContract, ValueContract, WorldContract,
)


class CentreOfMassPredictor(Predictor):
    """Stands when the new block's centre lies above its support's extent (a crude heuristic)."""

    def __init__(self, world, slack: float = 0.0):
        self.world, self.slack = world, slack

    def predict(self, state, actions, rng):
        out = []
        for a in actions:
            below = [b for b in state.geometry.blocks if b.layer == a.layer - 1]
            out.append(float(any(b.left - self.slack <= a.x <= b.right + self.slack for b in below)))
        return np.array(out)


class HeightValue(Value):
    def __init__(self, world):
        self.world = world

    def __call__(self, state):
        return float(max((b.layer for b in state.geometry.blocks), default=0))


class ThirdParty:
    """Registers one implementation of every kind, reusing the built-in world and planner classes."""

    def __init__(self, conf_dir):
        self.conf_dir = conf_dir

    @hookimpl
    def register_worlds(self, register):
        from overhang_builtins.world import OverhangWorld

        register("overhang_static", lambda **kw: OverhangWorld(physics="static", **kw))

    @hookimpl
    def register_predictors(self, register):
        register("centre", CentreOfMassPredictor)

    @hookimpl
    def register_planners(self, register):
        from overhang_builtins.myopic import MyopicPlanner

        register("greedy", MyopicPlanner)

    @hookimpl
    def register_values(self, register):
        register("height", HeightValue)

    @hookimpl
    def config_search_paths(self):
        return [f"file://{self.conf_dir}"]


@pytest.fixture
def third_party(register_plugin, tmp_path):
    for group, name, body in (("world", "overhang_static", ""), ("predictor", "centre", "slack: 0.0\n"),
                              ("planner", "greedy", ""), ("value", "height", "")):
        (tmp_path / group).mkdir()
        (tmp_path / group / f"{name}.yaml").write_text(f"name: {name}\n{body}")
    return register_plugin(ThirdParty(tmp_path), name="third-party")


def test_every_kind_is_registered_and_its_config_composes(third_party):
    cfg = compose_config(["world=overhang_static", "predictor=centre", "planner=greedy", "value=height",
                          "predictor.slack=0.1"])
    from overhang_framework.app import build_models

    models = build_models(cfg)
    assert type(models["predictor"]).__name__ == "CentreOfMassPredictor"
    assert models["predictor"].slack == 0.1
    assert models["world"].physics_name == "static"
    assert {n for n in Registry().names("value")} >= {"height", "overhang"}


class TestThirdPartyWorld(WorldContract):
    @pytest.fixture
    def world(self, third_party):
        return Registry().create("world", {"name": "overhang_static"})


class TestThirdPartyPredictor(PredictorContract):
    @pytest.fixture
    def predictor(self, world, third_party):
        return Registry().create("predictor", {"name": "centre"}, world=world)

    def test_heuristic_reads_the_support(self, predictor, world, state):
        top = max(b.layer for b in state.geometry.blocks)
        p = predictor.predict(state, [Action(0.0, top + 1), Action(1.5, top + 1)], np.random.default_rng(0))
        assert list(p) == [1.0, 0.0]


class TestThirdPartyPlanner(PlannerContract):
    @pytest.fixture
    def planner(self, world, third_party):
        return Registry().create("planner", {"name": "greedy"}, world=world)


class TestThirdPartyValue(ValueContract):
    @pytest.fixture
    def value(self, world, third_party):
        return Registry().create("value", {"name": "height"}, world=world)
