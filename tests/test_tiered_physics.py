"""The tiered physics gives the full-window reference's verdicts; the reference itself on hard towers."""

import numpy as np
import pytest

pytest.importorskip("pybullet")

from overhang_framework.physics.towers import FAMILIES, family_towers, find_flips, last_block_interval, with_last_x
from overhang_framework.geometry import Geometry
from overhang_framework.physics.factory import make_backend
from overhang_framework.physics.pybullet_backend import PyBulletParams, PyBulletSimulator
from overhang_framework.physics.static_backend import StaticBackend
from overhang_framework.physics.tiered import TieredBackend, TieredParams
from overhang_framework.plugins import Registry

EDGE = Geometry.from_tuples([(1.8, 0.0, 0), (1.8, 0.9, 1)])  # upper centre exactly above the lower edge
JAM = Geometry.from_tuples([(0.6, 0.0, 0), (0.6, -0.54, 1), (1.8, 0.08, 2), (0.6, 0.48, 1)])  # held by friction only


@pytest.fixture(scope="module")
def reference():
    sim = PyBulletSimulator(PyBulletParams(early_stop=False))
    yield lambda towers: np.array([sim.check(g).stable for g in towers])
    sim.close()


def world(**params):
    return Registry().create("world", {"name": "overhang", **params})


@pytest.mark.parametrize("params", [
    {},  # the default: tiered
    {"physics": "tiered", "workers": 2},
    {"physics": "pybullet"},  # the world's pybullet defaults to the full window
    {"physics": "pybullet", "pybullet": {"early_stop": False, "stop_on_fall": False}},
    {"physics": "pybullet", "pybullet": {"early_stop": False, "jitters": 2}},
], ids=["default", "tiered-pool", "pybullet", "pybullet-strict-window", "pybullet-robust"])
def test_the_edge_balanced_tower_falls_under_every_reference_setting(params):
    w = world(**params)
    assert w.physics_name == params.get("physics", "tiered")
    assert not w.is_stable(EDGE)
    assert not w.backend.stable_batch([EDGE])[0]


def test_early_stop_is_not_the_reference_on_the_edge_balanced_tower():
    sim = PyBulletSimulator(PyBulletParams())
    full, early = sim.check(EDGE, early_stop=False), sim.check(EDGE, early_stop=True)
    sim.close()
    assert not full.stable and full.steps < 5 / PyBulletParams().time_step  # fell before the window ended
    assert early.stable  # the rest test is fooled while the block creeps


def test_the_friction_jam_falls_in_the_reference_and_in_the_tiered_physics(reference):
    rigid = StaticBackend(margin=0.002, height_margin=0.0, friction_scale=1.0)  # the static model's old defaults
    assert rigid.stable(JAM)  # held by friction alone
    assert not rigid.stable(JAM, friction=[0.0] * len(JAM))
    assert not reference([JAM])[0]
    assert not StaticBackend().stable(JAM)  # the corrected static model (world.static defaults) drops it
    assert not world(physics="static").is_stable(JAM)
    backend = TieredBackend()
    assert backend.classify([JAM])[0] != 1  # never taken on the static model's word
    assert not backend.stable(JAM)


def test_static_stages_decide_clear_towers_without_the_reference():
    backend = TieredBackend()
    clear_stable = Geometry.from_tuples([(1.8, 0.0, 0), (1.2, 0.1, 1)])
    clear_fall = Geometry.from_tuples([(0.6, 0.0, 0), (1.8, 0.8, 1)])
    assert list(backend.stable_batch([clear_stable, clear_fall])) == [True, False]
    assert backend.stats() == {"static_stable": 1, "static_fall": 1, "reference": 0}
    assert backend._reference is None
    near_edge = [EDGE, Geometry.from_tuples([(1.8, 0.0, 0), (1.8, 0.895, 1)])]
    assert list(backend.classify(near_edge)) == [-1, -1]  # at or within the margin of an edge: the reference decides


def _near_static_flips(family, n, seed, rng):
    """Towers of ``family`` with their last block within 2 cm of the static model's flip (cheap to find)."""
    bases = family_towers(family, n, seed=seed)
    if family == "edge":
        return bases
    out = []
    for g, fx in zip(bases, find_flips(bases, StaticBackend().stable_batch, tolerance=0.002)):
        if fx is not None:
            lo, hi = last_block_interval(g)
            out.append(with_last_x(g, float(np.clip(fx + rng.uniform(-0.02, 0.02), lo, hi))))
    return out


@pytest.mark.parametrize("family", FAMILIES)
def test_tiered_equals_the_full_window_near_the_flip(family, reference):
    rng = np.random.default_rng(FAMILIES.index(family))
    towers = _near_static_flips(family, 6, seed=11, rng=rng)
    assert towers
    backend = TieredBackend()
    assert np.array_equal(backend.stable_batch(towers), reference(towers))


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_tiered_equals_the_full_window_near_the_reference_flip(family, reference):
    rng = np.random.default_rng(100 + FAMILIES.index(family))
    bases = family_towers(family, 12, seed=23)
    towers = bases if family == "edge" else [
        with_last_x(g, fx + rng.uniform(-0.02, 0.02))
        for g, fx in zip(bases, find_flips(bases, reference, tolerance=0.003)) if fx is not None
    ]
    backend = TieredBackend()
    decided = backend.classify(towers) >= 0
    assert np.array_equal(backend.stable_batch(towers), reference(towers))
    assert decided.any() or family == "edge"


def test_tiered_passes_gravity_and_friction_to_every_stage(reference):
    tower = Geometry.from_tuples([(1.8, 0.0, 0), (0.6, 0.0, 1)])
    backend = TieredBackend()
    slide = backend.stable_batch([tower, tower], gravity=np.array([[3.0, -9.81], [1.0, -9.81]]),
                                 friction=[[0.2, 0.2], [1.0, 1.0]])
    assert list(slide) == [False, True]


def test_factory_and_params():
    backend = make_backend("tiered", stable_margin=0.01, static={"friction": 0.4}, pybullet={"duration": 4.0},
                           cache=True)
    assert backend.name == "tiered"
    inner = backend.backend
    assert inner.tiers.stable_margin == 0.01 and inner.static_params.friction == 0.4
    assert inner.reference_params.duration == 4.0 and inner.reference_params.early_stop is False
    with pytest.raises(ValueError, match="stable_tilt"):
        TieredParams(stable_tilt=-0.1)
    with pytest.raises(ValueError, match="frictionless_stable"):
        TieredParams(frictionless_stable="yes")


def test_robust_verdict_needs_every_jitter_to_stand():
    near = Geometry.from_tuples([(1.8, 0.0, 0), (1.2, 0.9, 1)])  # centre on the edge
    sim = PyBulletSimulator(PyBulletParams(early_stop=False, jitters=2, jitter=0.001))
    out = sim.check(near)
    sim.close()
    assert not out.stable
    clear = Geometry.from_tuples([(1.8, 0.0, 0), (1.2, 0.2, 1)])
    sim = PyBulletSimulator(PyBulletParams(early_stop=False, duration=1.0, jitters=2))
    out = sim.check(clear)
    sim.close()
    assert out.stable and out.steps == 3 * 240


def test_world_config_lists_every_tiered_and_pybullet_parameter_with_its_default():
    from overhang_framework.config import compose_config

    world_cfg = compose_config([]).world
    assert world_cfg.physics == "tiered"
    for section, params in (("tiered", TieredParams()), ("pybullet", PyBulletParams())):
        listed = dict(world_cfg[section])
        assert set(listed) == set(params.__dataclass_fields__), section
        for name, value in listed.items():
            assert value == getattr(params, name), (section, name)
    for name in ("height_margin", "friction_scale", "margin"):
        assert world_cfg.static[name] == getattr(StaticBackend().params, name)


def test_the_veridical_predictor_plans_with_the_worlds_tiered_verdicts():
    reg = Registry()
    w = reg.create("world", {"name": "overhang"})
    predictor = reg.create("predictor", {"name": "veridical"}, world=w)
    assert predictor.backend is w.backend and w.backend.name == "tiered"
    from overhang_framework.interfaces import State
    from overhang_framework.geometry import Action

    state = State(Geometry.from_tuples([(1.8, 0.0, 0)]), (1.8,))
    p = predictor.predict(state, [Action(0.9, 1), Action(0.5, 1)], np.random.default_rng(0))
    assert list(p) == [0.0, 1.0]  # the edge placement the early-stop physics accepted is not stable
    assert w.stats()["cache"]["hits"] == 0 and w.is_stable(EDGE) is False and w.stats()["cache"]["hits"] == 1


#: Towers that the optimum searches of the benchmark's tasks asked about, which the "stands for sure" stage
#: called standing at its former tilt of 0.02 rad and the full-window reference topples: heavy loads on a
#: ground block of 0.6 (docs/physics.md, "A wider tilt for heavy loads on a narrow base"). With each, the
#: smallest tilt of the probe's grid at which the stage no longer calls it standing.
HEAVY_ON_NARROW = [
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.2, 0.1, 3), (1.8, -0.1, 4), (1.2, -0.9, 5)], 0.0275),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.2, 0.1, 3), (1.8, -0.4, 4), (1.8, -0.4, 5)], 0.0225),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.2, 0.1, 3), (1.8, -0.3, 4), (1.8, -0.5, 5)], 0.0225),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.2, 0.1, 3), (1.8, -0.1, 4), (1.8, -0.7, 5)], 0.0225),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.2, 0.1, 3), (1.8, 0.0, 4), (1.8, -0.8, 5)], 0.0225),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (1.8, 0.1, 3), (1.8, -0.7, 4), (0.6, -0.1, 5)], 0.0325),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (1.2, 0.0, 2), (1.8, 0.1, 3), (1.8, -0.7, 4), (0.6, -0.6, 5)], 0.0275),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (1.2, 0.1, 2), (1.8, 0.0, 3), (1.8, -0.8, 4)], 0.0225),
    ([(0.6, 0.0, 0), (0.6, 0.0, 1), (1.2, 0.2, 2), (1.8, 0.2, 3), (1.8, 0.4, 4)], 0.0225),
    ([(0.6, 0.0, 0), (1.2, 0.2, 1), (1.2, -0.3, 2), (1.8, -0.1, 3), (1.8, -0.7, 4)], 0.0225),
    ([(0.6, 0.0, 0), (1.2, 0.2, 1), (1.2, -0.3, 2), (1.8, 0.0, 3), (1.8, -0.8, 4)], 0.0225),
    ([(0.6, 0.0, 0), (1.2, 0.1, 1), (1.8, -0.2, 2), (1.8, 0.5, 3), (0.6, -0.4, 4), (1.8, -1.3, 3)], 0.025),
    ([(0.6, 0.0, 0), (1.8, 0.0, 1), (1.8, -1.3, 2), (1.2, 0.2, 2), (1.8, 0.2, 3), (1.2, -0.3, 4)], 0.025),
]


def test_heavy_loads_on_a_narrow_base_are_not_taken_on_the_static_models_word():
    towers = [Geometry.from_tuples(blocks) for blocks, _ in HEAVY_ON_NARROW]
    former = TieredBackend(TieredParams(stable_tilt=0.02)).classify(towers)
    assert (former == 1).all()  # the former setting called every one standing without asking the reference
    for (blocks, tilt), tower in zip(HEAVY_ON_NARROW, towers):
        assert TieredBackend(TieredParams(stable_tilt=tilt)).classify([tower])[0] != 1, blocks
        assert TieredBackend(TieredParams(stable_tilt=tilt - 0.0025)).classify([tower])[0] == 1, blocks
    assert TieredParams().stable_tilt >= 0.04
    assert (TieredBackend().classify(towers) == -1).all()  # each goes to the reference ...
    default = world()
    assert not any(default.is_stable(t) for t in towers)  # ... which topples it
