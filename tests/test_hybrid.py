"""The stage-switch hybrid predictor, and the headline command that uses it."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_builtins.hybrid import HybridPredictor
from overhang_framework.config import compose_config
from overhang_framework.geometry import Action, Block, Geometry
from overhang_framework.hookspecs import hookimpl
from overhang_framework.interfaces import Predictor, State
from overhang_framework.plugins import ConfigError, Registry, get_plugin_manager
from overhang_framework.testing.contracts import PredictorContract

ROOT = Path(__file__).resolve().parents[1]


def static_world():
    return Registry().create("world", {"name": "overhang", "physics": "static"})


class Constant(Predictor):
    """Answers ``value`` for every action and remembers the sizes of the towers it judged."""

    def __init__(self, world, value: float = 0.5):
        self.world = world
        self.value = value
        self.judged = []

    def predict(self, state, actions, rng):
        self.judged.extend(len(state.geometry) + 1 for _ in actions)
        return np.full(len(actions), self.value)


class ConstantPlugin:
    @hookimpl
    def register_predictors(self, register):
        register("test_low", lambda world, value=0.25: Constant(world, value))
        register("test_high", lambda world, value=0.75: Constant(world, value))


@pytest.fixture
def constants():
    pm = get_plugin_manager()
    plugin = ConstantPlugin()
    pm.register(plugin, name="test-constants")
    yield
    pm.unregister(plugin)


def tower(n_blocks: int, next_width: float = 0.6) -> State:
    blocks = tuple(Block(1.8, 0.0, layer) for layer in range(n_blocks))
    return State(Geometry(blocks), (next_width, 0.6))


def test_each_call_goes_to_the_predictor_of_the_judged_towers_size(constants):
    h = HybridPredictor(static_world(), early="test_low", late="test_high", switch=4)
    rng = np.random.default_rng(0)
    actions = [Action(0.0, 99)]  # the constant predictors never look at the action
    # towers after the action: 2, 3 -> early; 4, 5, 6 -> late
    answers = [float(h.predict(tower(n), actions * 2, rng)[0]) for n in (1, 2, 3, 4, 5)]
    assert answers == [0.25, 0.25, 0.75, 0.75, 0.75]
    assert h.early.judged == [2, 2, 3, 3] and h.late.judged == [4, 4, 5, 5, 6, 6]
    stats = h.stats()
    assert stats["early_calls"] == 2 and stats["late_calls"] == 3
    assert stats["early_actions"] == 4 and stats["late_actions"] == 6
    assert (stats["early"], stats["late"], stats["switch"]) == ("test_low", "test_high", 4)


def test_many_requests_are_split_by_size_and_answered_in_order(constants):
    h = HybridPredictor(static_world(), early="test_low", late="test_high", switch=4)
    actions = [Action(0.0, 99)]
    requests = [(tower(n), actions * n) for n in (4, 1, 3, 2)]  # towers after the action: 5, 2, 4, 3
    answers = h.predict_many(requests, [np.random.default_rng(i) for i in range(4)])
    assert [a.tolist() for a in answers] == [[0.75] * 4, [0.25], [0.75] * 3, [0.25] * 2]
    stats = h.stats()
    assert (stats["early_calls"], stats["late_calls"]) == (2, 2)
    assert (stats["early_actions"], stats["late_actions"]) == (3, 7)


def test_parameters_reach_the_composed_predictors(constants):
    h = HybridPredictor(static_world(), early="test_low", late="test_high", switch=2,
                        early_params={"value": 0.1}, late_params={"value": 0.9})
    rng = np.random.default_rng(0)
    assert h.predict(tower(1), [Action(0.0, 1)], rng)[0] == 0.9  # a 2-block tower is already late
    assert h.early.value == 0.1


def test_inside_a_lookahead_deeper_towers_go_to_late(constants):
    world = static_world()
    registry = Registry()
    h = registry.create("predictor", {"name": "hybrid", "early": "veridical", "late": "test_high",
                                      "switch": 3}, world=world)
    planner = registry.create("planner", {"name": "lookahead", "depth": 2}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    from overhang_framework.interfaces import Budget

    state = State(Geometry((Block(1.8, 0.0, 0),)), (1.2, 0.6, 0.6))
    planner.plan(state, h, value, Budget(), np.random.default_rng(0))
    stats = h.stats()
    assert stats["early_calls"] == 1  # the root: towers of 2 blocks
    assert stats["late_calls"] >= 1 and set(h.late.judged) == {3}


def test_bad_hybrid_settings_are_refused():
    world = static_world()
    registry = Registry()
    with pytest.raises(ConfigError, match="unknown early predictor 'oracle'; allowed: .*ipe"):
        registry.create("predictor", {"name": "hybrid", "early": "oracle"}, world=world)
    with pytest.raises(ConfigError, match="late cannot be 'hybrid' itself"):
        registry.create("predictor", {"name": "hybrid", "late": "hybrid"}, world=world)
    with pytest.raises(ConfigError, match="switch must be a whole number of blocks >= 1"):
        registry.create("predictor", {"name": "hybrid", "switch": 0}, world=world)
    with pytest.raises(ConfigError, match="predictor 'ipe' has no parameter colour"):
        registry.create("predictor", {"name": "hybrid", "early_params": {"colour": 1}}, world=world)


def test_the_hybrid_config_builds_ipe_then_cnn():
    cfg = compose_config(["predictor=hybrid", "world.physics=static"])
    from overhang_framework.plugins import build_models

    predictor = build_models(cfg)["predictor"]
    assert type(predictor.early).__name__ == "IPEPredictor" and predictor.early.K == 50
    assert type(predictor.late).__name__ == "CNNPredictor" and predictor.switch == 4


class TestHybridContract(PredictorContract):
    @pytest.fixture
    def world(self):
        return static_world()

    @pytest.fixture
    def predictor(self, world):
        return Registry().create("predictor", {"name": "hybrid", "switch": 3,
                                               "early_params": {"K": 10}, "late_params": {"device": "cpu"}},
                                 world=world)


def headline(tmp_path, *extra):
    return subprocess.run(
        [sys.executable, "-m", "overhang_framework", "predictor=hybrid", "planner=lookahead",
         "planner.depth=3", "tasks.only=[paper00]", "progress=false", f"hydra.run.dir={tmp_path}", *extra],
        cwd=ROOT, capture_output=True, text=True, timeout=1800)


@pytest.fixture(scope="module")
def hybrid_runs(tmp_path_factory):
    """Two short runs of the hybrid from the command line, at once: the headline command on a 4-block task, and
    the default planner on another."""
    from commands import run_each

    base = tmp_path_factory.mktemp("hybrid_runs")
    common = [sys.executable, "-m", "overhang_framework", "predictor=hybrid", "tasks=custom", "world.physics=static",
              "progress=false"]
    headline_run, default_run = run_each([
        [*common, "planner=lookahead", "planner.depth=3", "tasks.sequences=[[1.8,1.2,0.6,0.6]]",
         f"hydra.run.dir={base / 'headline'}"],
        [*common, "tasks.sequences=[[1.2,0.6,1.8,0.6]]", f"hydra.run.dir={base / 'default'}"]], timeout=900, cwd=ROOT)
    return {"headline": (headline_run, base / "headline"), "default": (default_run, base / "default")}


def test_the_headline_command_runs_on_a_short_task(hybrid_runs):
    """The headline command on a 4-block task: its first depth-3 decision asks both predictors."""
    out, where = hybrid_runs["headline"]
    assert out.returncode == 0, out.stderr[-2000:]
    metrics = json.loads((where / "metrics.json").read_text())
    assert metrics["complete"] and metrics["episodes_expected"] == 1
    assert metrics["config"]["predictor"] == "hybrid"


@pytest.mark.slow
def test_the_headline_command_runs_on_one_task_static_physics(tmp_path):
    out = headline(tmp_path, "world.physics=static")
    assert out.returncode == 0, out.stderr[-2000:]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["complete"] and metrics["episodes_expected"] == 1
    assert metrics["config"]["predictor"] == "hybrid"


@pytest.mark.slow
def test_the_headline_command_runs_on_one_task(tmp_path):
    out = headline(tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["complete"] and metrics["world_stats"]["physics"] == "tiered"


def test_a_run_records_which_predictor_answered(hybrid_runs):
    proc, where = hybrid_runs["default"]
    assert proc.returncode == 0, proc.stderr
    stats = json.loads((where / "metrics.json").read_text())["predictor_stats"]
    # towers of 2 and 3 blocks go to the early predictor, the 4-block one to the late one
    assert (stats["early_calls"], stats["late_calls"]) == (2, 1)


def test_the_switch_analysis_scores_each_predictor_by_blocks(tmp_path, capsys):
    from overhang_framework.analyses.predictor_accuracy import main

    out = main(["--out", str(tmp_path), "--quick", "--predictors", "ipe,veridical", "--max-blocks", "4",
                "--no-progress"])
    rows = {(r["predictor"], r["n_blocks"]): r for r in out["summary"]}
    assert sorted(rows) == [(p, n) for p in ("ipe", "veridical") for n in (2, 3, 4)]
    # veridical simulates the quick run's static reference, so it is never wrong and the switch is at 2
    assert all(rows[("veridical", n)]["accuracy"] == 1.0 for n in (2, 3, 4))
    assert out["meta"]["switch_point"] == 2
    assert "veridical is at least as accurate as ipe from 2 blocks on" in capsys.readouterr().out
    assert (tmp_path / "predictor_accuracy.png").read_bytes()[:4] == b"\x89PNG"
    assert len((tmp_path / "predictor_accuracy.csv").read_text().splitlines()) == 1 + 6
