"""The practice towers a person can build: the stored ones stay legal and stand under the reference with every
placement off by the tolerance, the optimal towers they replace do not, no better tower on the world's grid
does, and the server will not start without them."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import pytest

from overhang_framework import rules
from overhang_framework.errors import ConfigError
from overhang_framework.experiment.practice import (
    COMMAND,
    BuildableSearch,
    legal_throughout,
    load_towers,
    tower_key,
)
from overhang_framework.experiment.settings import ADMIN_ENV, compose, load_settings
from overhang_framework.geometry import Action, Block, Geometry, overhang
from overhang_framework.interfaces import Task
from overhang_framework.plugins import Registry
from overhang_framework.search import reach_bound


@pytest.fixture(autouse=True)
def no_admin_env(monkeypatch):
    monkeypatch.delenv(ADMIN_ENV, raising=False)


@pytest.fixture(scope="module")
def settings(tmp_path_factory):
    return load_settings([f"run_dir={tmp_path_factory.mktemp('run')}", "admin_token=long-enough-token"])


@pytest.fixture(scope="module")
def reference(settings):
    return Registry().create("world", {**settings.world, "physics": "pybullet"})


def corner_failure(world, tower, tolerance, steps=3):
    """Why ``tower`` ([width, x, layer], ground first, in placement order) fails: some prefix with its
    placements off by a combination of -tol, 0, +tol (``steps`` evenly spaced offsets from -tol to +tol) is
    illegal or falls under ``world``; None if none."""
    ground, placed = Block(*tower[0]), tower[1:]
    grid = [tolerance * (2 * i / (steps - 1) - 1) for i in range(steps)]
    for k in range(1, len(placed) + 1):
        for offsets in itertools.product(grid, repeat=k):
            blocks = [ground] + [Block(w, round(x + d, 9), layer) for (w, x, layer), d in zip(placed, offsets)]
            last = blocks[-1]
            why = rules.illegal_reason(Geometry(tuple(blocks[:-1])), last.width, Action(last.x, last.layer))
            if why:
                return f"{offsets}: {why}"
            if not world.is_stable(Geometry(tuple(blocks))):
                return f"{offsets}: falls"
    return None


def better_towers(world, task, reward):
    """Every tower on the world's grid that stands after each placement (unperturbed) and beats ``reward``."""
    out = []

    def visit(state, blocks):
        if state.done:
            if overhang(state.geometry) > reward + 1e-9:
                out.append([[b.width, b.x, b.layer] for b in state.geometry.blocks])
            return
        for action in world.legal_actions(state):
            child = world.successor(state, action)
            if reach_bound(world, child, len(child.remaining)) > reward + 1e-9 and world.is_stable(child.geometry):
                visit(child, blocks)

    visit(world.initial_state(task), [])
    return out


@pytest.mark.slow
def test_stored_towers_stay_legal_and_stand_under_the_reference_with_every_placement_off(settings, reference):
    assert len(settings.practice) == 3
    for practice in settings.practice:
        assert practice.tolerance == compose().practice.tolerance > 0
        assert corner_failure(reference, practice.shown_tower, practice.tolerance) is None, practice.task.id


@pytest.mark.slow
def test_stored_towers_also_stand_between_the_corners(settings, reference):
    for practice in settings.practice:  # five offsets per placement: 5 + 25 + 125 towers each
        assert corner_failure(reference, practice.shown_tower, practice.tolerance, steps=5) is None, practice.task.id


def test_the_shown_tower_is_what_the_file_holds_and_passing_is_judged_against_it(settings):
    towers = load_towers()
    world = Registry().create("world", settings.world)
    for practice in settings.practice:
        row = towers[tower_key(practice.task, world, practice.tolerance)]
        assert practice.shown_tower == row["tower"] and row["tolerance"] == practice.tolerance
        assert [b[0] for b in practice.shown_tower] == list(practice.task.sequence)
        assert practice.shown_reward == pytest.approx(overhang(Geometry.from_tuples(practice.shown_tower)))
        assert practice.shown_reward <= practice.optimum + 1e-9
        ground = overhang(Geometry.from_tuples(practice.shown_tower[:1]))
        assert ground < practice.pass_reward < practice.shown_reward  # more than standing, less than the shown tower
        assert practice.pass_reward == pytest.approx(ground + settings.practice_threshold
                                                     * (practice.shown_reward - ground))


def test_the_optimal_towers_that_are_not_shown_fail_the_check(settings, reference):
    replaced = [p for p in settings.practice if p.shown_reward < p.optimum - 1e-9]
    assert replaced, "every practice optimum passes the check; the shown towers would be the optima"
    for practice in replaced:
        assert corner_failure(reference, practice.optimal_tower, practice.tolerance) is not None, practice.task.id


def test_no_better_tower_on_the_grid_passes_the_check(settings):
    world = Registry().create("world", settings.world)
    for practice in settings.practice:
        better = better_towers(world, practice.task, practice.shown_reward)
        assert all(corner_failure(world, tower, practice.tolerance) for tower in better), practice.task.id


@pytest.mark.parametrize("tolerance", [0.0, 0.05])
def test_the_search_finds_the_best_tower_that_passes(tolerance):
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    task = Task("t", (1.8, 1.2, 0.6, 1.2))
    found = BuildableSearch(world, tolerance, reference=False).best(task)
    state = world.initial_state(task)
    for action in found.actions:
        state = world.successor(state, action)
    tower = [[b.width, b.x, b.layer] for b in state.geometry.blocks]
    assert len(found.actions) == 3 and found.reward == pytest.approx(overhang(state.geometry))
    assert corner_failure(world, tower, tolerance) is None
    better = better_towers(world, task, found.reward)
    assert all(corner_failure(world, t, tolerance) for t in better)
    # with no error allowed the best tower that passes is an optimum; with one, better towers exist and fail
    assert (better == []) == (tolerance == 0)


def test_legality_is_checked_for_every_offset_within_the_tolerance():
    ground, a = Block(1.8, 0.0, 0), Block(0.6, -0.3, 1)
    assert legal_throughout(ground, [a], 0.02) is None
    assert "may overlap" in legal_throughout(ground, [a, Block(0.6, 0.3, 1)], 0.02)  # touching at x = 0
    assert legal_throughout(ground, [a, Block(0.6, 0.35, 1)], 0.02) is None  # 0.05 apart, closer by 0.04 at most
    assert "may overlap" in legal_throughout(ground, [a, Block(0.6, 0.33, 1)], 0.02)  # 0.03 apart
    # support: 0.03 of overlap on the ground (which never moves) survives 0.02; on a placed block it may not
    assert legal_throughout(ground, [Block(0.6, 1.17, 1)], 0.02) is None
    assert "supports" in legal_throughout(ground, [a, Block(0.6, -0.87, 2)], 0.02)


def test_the_server_needs_the_towers_of_its_tolerance(tmp_path):
    with pytest.raises(ConfigError) as err:
        load_settings([f"run_dir={tmp_path}", "admin_token=long-enough-token", "practice.tolerance=0.03"])
    message = str(err.value)
    assert "\n" not in message and f"{COMMAND} world.physics=tiered practice.tolerance=0.03" in message


@pytest.mark.parametrize("value", [-0.01, 0.3, "'two pixels'"])
def test_a_bad_tolerance_is_one_line(tmp_path, value):
    with pytest.raises(ConfigError) as err:
        load_settings([f"run_dir={tmp_path}", "admin_token=long-enough-token", f"practice.tolerance={value}"])
    assert str(err.value).startswith("practice.tolerance must be a number of units in [0, 0.3)")


def test_the_command_stores_each_tower_once(tmp_path):
    out = tmp_path / "towers.json"
    args = [sys.executable, "-m", "overhang_framework.experiment.practice", "--out", str(out), "world.physics=static",
            "practice.sequences=[[1.8,1.2,0.6]]", "practice.ids=[t1]", "practice.tolerance=0.05"]
    first = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    rows = json.loads(out.read_text())["towers"]
    (row,) = rows.values()
    assert row["task_id"] == "t1" and row["physics"] == "static" and row["tolerance"] == 0.05
    assert 0 < row["reward"] <= row["optimum"] and row["command"].startswith(COMMAND)
    assert "t1  1.8 1.2 0.6  tolerance 0.05  reward" in first.stdout
    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and json.loads(out.read_text())["towers"] == rows
    bad = subprocess.run([*args, "practice.tolerance=1"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        "error: practice.tolerance must be a number of units in [0, 0.3), got 1"]
