"""The optimum: equal to brute force on small tasks, cached on disk, and the optimal planner plays it."""

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from overhang_framework.geometry import overhang
from overhang_framework.interfaces import Budget, Task
from overhang_framework.optimum import OptimumSearch, load_optima, optimum_key, task_optimum
from overhang_framework.plugins import Registry

REG = Registry()


@pytest.fixture(scope="module")
def world():
    return REG.create("world", {"name": "overhang", "physics": "static", "resolution": 0.2})


@pytest.fixture(scope="module")
def veridical(world):
    return REG.create("predictor", {"name": "veridical"}, world=world)


def brute_force(world, state) -> float:
    """The best final overhang over every sequence of legal placements that stands throughout."""
    if state.done:
        return overhang(state.geometry)
    best = 0.0
    for action in world.legal_actions(state):
        child = world.successor(state, action)
        if world.is_stable(child.geometry):
            best = max(best, brute_force(world, child))
    return best


@pytest.mark.parametrize("sequence", [(0.6, 1.8, 1.2, 0.6), (1.2, 0.6, 1.8, 1.8), (1.8, 1.2, 0.6, 1.2),
                                      (0.6, 0.6, 1.8, 1.2)])
def test_the_optimum_equals_brute_force(world, veridical, sequence):
    state = world.initial_state(Task("t", sequence))
    search = OptimumSearch(world, veridical)
    assert search.value_of(state) == pytest.approx(brute_force(world, state))
    unmirrored = OptimumSearch(world, veridical, mirror=False)
    assert unmirrored.value_of(state) == pytest.approx(search.value_of(state))


def test_mirror_symmetry_halves_the_first_expansion(world, veridical):
    state = world.initial_state(Task("t", (1.2, 1.8, 0.6)))
    mirrored = OptimumSearch(world, veridical, mirror=True).expander.expand(state)
    plain = OptimumSearch(world, veridical, mirror=False).expander.expand(state)
    assert all(a.x >= 0 for a in mirrored.actions)
    assert len(mirrored.actions) == sum(a.x >= 0 for a in plain.actions) < len(plain.actions)


def test_the_optimal_planner_reaches_the_optimum(world, veridical):
    value = REG.create("value", {"name": "overhang"}, world=world)
    planner = REG.create("planner", {"name": "optimal"}, world=world)
    task = Task("t", (1.2, 0.6, 1.8, 1.8))
    state = world.initial_state(task)
    rng = np.random.default_rng(0)
    while not state.done:
        state = world.step(state, planner.plan(state, veridical, value, Budget(), rng).action)
        assert world.is_stable(state.geometry)
    assert overhang(state.geometry) == pytest.approx(brute_force(world, world.initial_state(task)))


def test_optima_are_cached_on_disk_by_task_physics_and_resolution(tmp_path, world):
    out = tmp_path / "optima.json"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.optimum", "tasks=custom",
                           "tasks.sequences=[[0.6,1.8,1.2],[1.2,0.6,0.6]]", "world.physics=static",
                           "world.resolution=0.2", f"--out={out}"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    optima = load_optima(out)
    assert len(optima) == 2
    task = Task("custom00", (0.6, 1.8, 1.2))
    row = optima[optimum_key(task, world)]
    assert row["optimum"] == pytest.approx(brute_force(world, world.initial_state(task)))
    assert task_optimum(task, world, path=out) == row
    coarser = REG.create("world", {"name": "overhang", "physics": "static", "resolution": 0.3})
    assert optimum_key(task, coarser) not in optima
    again = subprocess.run([sys.executable, "-m", "overhang_framework.optimum", "tasks=custom",
                            "tasks.sequences=[[0.6,1.8,1.2],[1.2,0.6,0.6]]", "world.physics=static",
                            "world.resolution=0.2", f"--out={out}"], capture_output=True, text=True)
    assert again.returncode == 0 and json.loads(out.read_text())["optima"] == optima


def test_the_optimal_planner_replays_stored_optimal_paths(tmp_path, world, veridical, monkeypatch):
    import overhang_framework.optimum as optimum

    task = Task("t", (1.2, 0.6, 1.8, 1.8))
    row = task_optimum(task, world, path=None)
    out = tmp_path / "optima.json"
    out.write_text(json.dumps({"optima": {optimum_key(task, world): row}}))
    monkeypatch.setattr(optimum, "DATA_FILE", out)
    value = REG.create("value", {"name": "overhang"}, world=world)
    played = {}
    for stored in (True, False):
        planner = REG.create("planner", {"name": "optimal", "stored": stored}, world=world)
        state, actions, calls = world.initial_state(task), [], 0
        while not state.done:
            d = planner.plan(state, veridical, value, Budget(), np.random.default_rng(0))
            calls += d.spend.predictor_calls
            actions.append(d.action)
            state = world.step(state, d.action)
        played[stored] = (overhang(state.geometry), calls)
    assert played[True][0] == played[False][0] == pytest.approx(row["optimum"])
    assert played[True][1] == 3 < played[False][1], "stored paths are replayed with one check per placement"


@pytest.mark.parametrize("physics", ["static", "tiered"])
def test_the_shipped_optima_are_found_under_every_engine_setting(physics):
    # how the static engine computes a verdict (its stages, its least squares) is not part of the key
    from overhang_framework.optimum import optimal_moves

    default = optimal_moves(REG.create("world", {"name": "overhang", "physics": physics}))
    assert len(default) > 50
    if physics == "static":
        for setting in ({"nnls": "scipy"}, {"compiled": False}, {"lp_nnls": False}):
            other = REG.create("world", {"name": "overhang", "physics": "static", "static": setting})
            assert optimal_moves(other) == default, setting
