"""The PyBullet reference on towers whose fate is known, and early stopping against the full run."""

import pytest

pytest.importorskip("pybullet")

from overhang_framework.geometry import Geometry
from overhang_framework.physics.pybullet_backend import (
    PyBulletParams,
    PyBulletSimulator,
)
from overhang_framework.physics.towers import random_towers


@pytest.fixture(scope="module")
def sim():
    s = PyBulletSimulator(PyBulletParams())
    yield s
    s.close()


STABLE = [
    [(1.2, 0.0, 0)],
    [(0.6, 0.0, 0), (1.2, 0.2, 1)],
    [(1.8, 0.0, 0), (0.6, -0.6, 1), (0.6, 0.6, 1), (1.8, 0.0, 2)],
    [(0.6, 0.0, 0), (1.8, 0.45, 1), (1.2, -0.15, 2)],
]
FALLING = [
    [(0.6, 0.0, 0), (1.2, 0.4, 1)],
    [(1.8, 0.0, 0), (0.6, 1.05, 1)],
    [(0.6, 0.0, 0), (1.8, 0.45, 1)],
]


@pytest.mark.parametrize("rows", STABLE)
def test_known_stable_towers_stand(sim, rows):
    out = sim.check(Geometry.from_tuples(rows), early_stop=False)
    assert out.stable and out.displacement < 0.01


@pytest.mark.parametrize("rows", FALLING)
def test_known_unstable_towers_fall(sim, rows):
    out = sim.check(Geometry.from_tuples(rows), early_stop=False)
    assert not out.stable and out.displacement > 0.05


def test_tilted_gravity_with_low_friction_slides(sim):
    tower = Geometry.from_tuples([(1.8, 0.0, 0), (0.6, 0.0, 1)])
    assert not sim.check(tower, gravity=(3.0, -9.81), friction=[0.2, 0.2], early_stop=False).stable
    assert sim.check(tower, gravity=(1.0, -9.81), friction=[1.0, 1.0], early_stop=False).stable


def test_early_stop_agrees_with_the_full_run(sim):
    towers = random_towers(10, seed=12, max_blocks=5) + [Geometry.from_tuples(r) for r in STABLE + FALLING]
    full = [sim.check(g, early_stop=False) for g in towers]
    early = [sim.check(g, early_stop=True) for g in towers]
    assert [o.stable for o in early] == [o.stable for o in full]
    assert sum(o.steps for o in early) < sum(o.steps for o in full)


def test_a_tower_balanced_exactly_on_an_edge_is_not_called_stable_early(sim):
    tower = Geometry.from_tuples([(0.6, 0.0, 0), (1.2, -0.3, 1)])
    assert not sim.check(tower, early_stop=False).stable
    assert not sim.check(tower, early_stop=True).stable
