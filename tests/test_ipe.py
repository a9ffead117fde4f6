"""The Intuitive Physics Engine predictor (``ipe``) and its noise-free case (``veridical``)."""

import numpy as np
import pytest
from scipy.stats import norm

from overhang_builtins.simulation import Draws, IPEPredictor, VeridicalPredictor, separate_overlaps
from overhang_framework.config import compose_config
from overhang_framework.geometry import Action, Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import Registry
from overhang_framework.testing.contracts import PredictorContract


def static_world(cache=True):
    return Registry().create("world", {"name": "overhang", "physics": "static", "cache": cache})


def ipe(world, **params):
    return Registry().create("predictor", {"name": "ipe", "backend": "static", **params}, world=world)


BASE = Block(1.8, 0.0, 0)  # its right edge is at x = 0.9


def on_base(width=0.6):
    """The ground block of width 1.8 with a block of ``width`` still to place."""
    return State(Geometry((BASE,)), (width,))


def tall_state():
    """A 4-block tower, centred, with a 0.6 block to place on top (layer 4)."""
    blocks = (Block(1.8, 0.0, 0), Block(1.2, 0.0, 1), Block(1.8, 0.0, 2), Block(1.2, 0.0, 3))
    return State(Geometry(blocks), (0.6,))


@pytest.fixture(scope="module")
def world():
    return static_world()


class _OnStaticWorld(PredictorContract):
    @pytest.fixture
    def world(self):
        return static_world()


class TestIPEContract(_OnStaticWorld):
    @pytest.fixture
    def predictor(self, world):
        return ipe(world)


class TestVeridicalContract(_OnStaticWorld):
    @pytest.fixture
    def predictor(self, world):
        return Registry().create("predictor", {"name": "veridical"}, world=world)


def test_the_ipe_config_builds_the_paper_model():
    cfg = compose_config(["predictor=ipe"])
    model = Registry().create("predictor", cfg.predictor, world=static_world())
    assert isinstance(model, IPEPredictor)
    assert model.K == 50
    assert (model.noise.position, model.noise.gravity, model.noise.friction) == (0.03, 0.03, 0.03)
    assert model.backend.name == "static"


def test_per_channel_sigma_overrides_the_common_one(world):
    model = ipe(world, sigma=0.05, sigma_gravity=0.0)
    assert (model.noise.position, model.noise.gravity, model.noise.friction) == (0.05, 0.0, 0.05)


@pytest.mark.parametrize("bad", [{"sigma": -0.01}, {"K": 0}, {"backend": "newtonian"}, {"sigma": float("nan")}])
def test_invalid_parameters_are_refused(world, bad):
    with pytest.raises(ValueError):
        ipe(world, **bad)


@pytest.mark.parametrize("sigma", [0.0, 0.03, 0.3])
def test_probabilities_lie_in_the_unit_interval(world, sigma):
    state = tall_state()
    actions = world.legal_actions(state)
    p = ipe(world, sigma=sigma, K=20).predict(state, actions, np.random.default_rng(1))
    assert p.shape == (len(actions),)
    assert np.all((p >= 0) & (p <= 1))
    assert set(np.round(p * 20, 9)) <= set(range(21))  # multiples of 1/K


@pytest.mark.parametrize("backend", ["static", "world"])
def test_sigma_zero_gives_the_veridical_verdicts(world, backend):
    state = tall_state()
    actions = world.legal_actions(state)
    p = ipe(world, sigma=0.0, backend=backend).predict(state, actions, np.random.default_rng(0))
    v = VeridicalPredictor(world).predict(state, actions, np.random.default_rng(0))
    assert set(np.unique(p)) == {0.0, 1.0}
    np.testing.assert_array_equal(p, v)


def test_sigma_zero_gives_the_veridical_verdicts_on_pybullet():
    pyworld = Registry().create("world", {"name": "overhang", "physics": "pybullet", "cache": False})
    state = on_base()
    actions = [Action(x, 1) for x in (0.0, 0.5, 0.85, 0.95, 1.1)]
    p = IPEPredictor(pyworld, sigma=0.0, backend="pybullet").predict(state, actions, np.random.default_rng(0))
    v = VeridicalPredictor(pyworld).predict(state, actions, np.random.default_rng(0))
    np.testing.assert_array_equal(p, v)
    np.testing.assert_array_equal(p, [1, 1, 1, 0, 0])


def test_a_vanishing_sigma_converges_to_the_veridical_verdicts(world):
    state = tall_state()
    actions = world.legal_actions(state)
    v = VeridicalPredictor(world).predict(state, actions, None)
    shifted = [VeridicalPredictor(world).predict(state, [Action(a.x + d, a.layer) for a in actions], None)
               for d in (-0.01, 0.01)]
    clear = (shifted[0] == v) & (shifted[1] == v)  # not within 0.01 of a flip
    assert clear.sum() > 10 and (v[clear] == 1).any() and (v[clear] == 0).any()
    p = ipe(world, sigma=1e-6).predict(state, actions, np.random.default_rng(0))
    np.testing.assert_array_equal(p[clear], v[clear])


def test_clearly_stable_and_clearly_falling_towers(world):
    state = tall_state()
    actions = [Action(0.0, 4), Action(0.9, 4)]  # centred; 0.3 beyond the edge of the 1.2 below
    p = ipe(world).predict(state, actions, np.random.default_rng(0))
    assert p[0] >= 0.95
    assert p[1] <= 0.05


def test_a_tower_at_its_tipping_point_scores_in_between(world):
    state = on_base()
    veridical = VeridicalPredictor(world)
    assert veridical.predict(state, [Action(0.89, 1), Action(0.91, 1)], None).tolist() == [1.0, 0.0]
    p = ipe(world).predict(state, [Action(0.9, 1)], np.random.default_rng(0))[0]
    assert 0.2 < p < 0.8


def test_position_noise_is_an_x_offset_in_metres_per_block(world):
    d, sigma = 0.03, 0.03
    model = ipe(world, sigma=0.0, sigma_position=sigma, K=4000, backend_params={"margin": 0.0})
    p = model.predict(on_base(), [Action(0.9 - d, 1)], np.random.default_rng(2))[0]
    # top and ground block each shifted by N(0, sigma^2): it stands while their difference is below d
    assert p == pytest.approx(norm.cdf(d / (sigma * np.sqrt(2))), abs=0.03)


def test_gravity_noise_is_a_tilt_in_radians_per_simulation(world):
    d, sigma = 0.009, 0.03
    model = ipe(world, sigma=0.0, sigma_gravity=sigma, K=4000, backend_params={"margin": 0.0})
    p = model.predict(on_base(), [Action(0.9 - d, 1)], np.random.default_rng(3))[0]
    # the block's centre is 0.3 above its contact: a tilt theta moves its load by 0.3 tan(theta)
    assert p == pytest.approx(norm.cdf(np.arctan(d / 0.3) / sigma), abs=0.03)


def test_the_perturbations_have_the_documented_scales(world):
    sigma, K = 0.05, 20000
    model = ipe(world, sigma=sigma, K=K)
    state = on_base()
    draws = Draws.sample(np.random.default_rng(4), K, 2)
    scenes, gravity, friction = model.perturb(model.successors(state, [Action(0.0, 1)]), draws)
    xs = np.array([[b.x for b in g.blocks] for g in scenes])
    assert np.std(xs, axis=0) == pytest.approx([sigma, sigma], rel=0.03)
    assert [g.blocks[1].layer for g in scenes[:5]] == [1] * 5
    theta = np.arctan2(gravity[:, 0], -gravity[:, 1])
    scale = np.hypot(gravity[:, 0], gravity[:, 1]) / 9.81
    assert np.std(theta) == pytest.approx(sigma, rel=0.03) and abs(np.mean(theta)) < 0.002
    assert np.std(scale) == pytest.approx(sigma, rel=0.03) and np.mean(scale) == pytest.approx(1, abs=0.002)
    assert friction.shape == (K, 2)
    assert np.mean(friction) == pytest.approx(0.5, abs=0.002)
    assert np.std(friction) == pytest.approx(sigma, rel=0.03)


def test_blocks_of_one_layer_are_pushed_apart_not_interpenetrating():
    widths, layers, ref = np.array([0.6, 0.6, 1.2]), np.array([1, 1, 0]), np.array([0.0, 0.6, 0.3])
    xs = np.array([[0.02, 0.58, 0.3], [-0.01, 0.62, 0.31], [0.05, 0.56, 0.2]])
    out = separate_overlaps(xs, widths, layers, ref)
    np.testing.assert_array_equal(out[1], xs[1])  # no overlap: unchanged
    for row, orig in ((out[0], xs[0]), (out[2], xs[2])):
        assert row[1] - row[0] == pytest.approx(0.6)  # touching
        assert row[0] + row[1] == pytest.approx(orig[0] + orig[1])  # least displacement
        assert row[2] == orig[2]


def test_three_touching_blocks_are_separated_least_squares():
    widths, layers, ref = np.full(3, 0.6), np.ones(3, dtype=int), np.array([0.0, 0.6, 1.2])
    xs = np.array([[0.03, 0.6, 1.17]])
    out = separate_overlaps(xs, widths, layers, ref)
    np.testing.assert_allclose(out[0], [0.0, 0.6, 1.2], atol=1e-12)


def test_touching_neighbours_stay_standing_under_position_noise(world):
    state = State(Geometry((Block(1.8, 0.0, 0), Block(0.6, -0.3, 1))), (0.6,))
    p = ipe(world).predict(state, [Action(0.3, 1)], np.random.default_rng(0))[0]
    assert p >= 0.95


def test_results_repeat_for_a_seed_and_change_with_it(world):
    model = ipe(world)
    state, actions = on_base(), [Action(x, 1) for x in (0.86, 0.88, 0.9, 0.92, 0.94)]
    a = model.predict(state, actions, np.random.default_rng(11))
    b = model.predict(state, actions, np.random.default_rng(11))
    c = model.predict(state, actions, np.random.default_rng(12))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_batched_equals_one_by_one_near_the_tipping_point(world):
    model = ipe(world)
    state = on_base()
    actions = [Action(float(x), 1) for x in np.round(np.arange(0.8, 1.01, 0.02), 2)]
    batched = model.predict(state, actions, np.random.default_rng(5))
    single = [model.predict(state, [a], np.random.default_rng(5))[0] for a in actions]
    np.testing.assert_array_equal(batched, single)
    assert ((batched > 0) & (batched < 1)).sum() >= 3


def test_common_random_numbers_make_stability_monotone_in_x(world):
    state = on_base()
    actions = [Action(float(x), 1) for x in np.round(np.arange(0.8, 1.01, 0.01), 2)]
    p = ipe(world).predict(state, actions, np.random.default_rng(6))
    assert np.all(np.diff(p) <= 0)
    assert p[0] == 1.0 and p[-1] == 0.0


def test_changing_one_sigma_keeps_the_other_channels_draws(world):
    state = on_base()
    geoms = IPEPredictor(world).successors(state, [Action(0.5, 1)])
    a = ipe(world, sigma_gravity=0.0).scenes(state, [Action(0.5, 1)], np.random.default_rng(8))
    b = ipe(world, sigma_gravity=0.1).scenes(state, [Action(0.5, 1)], np.random.default_rng(8))
    assert geoms and a.gravity is None and b.gravity is not None
    assert [g.key for g in a.geometries] == [g.key for g in b.geometries]
    np.testing.assert_array_equal(a.friction, b.friction)


def test_noisy_world_backend_leaves_the_world_cache_alone():
    w = static_world(cache=True)
    state = tall_state()
    actions = w.legal_actions(state)
    p = ipe(w, backend="world").predict(state, actions, np.random.default_rng(0))
    assert len(w.backend.cache) == 0
    assert ((p > 0) & (p < 1)).any()
    VeridicalPredictor(w).predict(state, actions, None)
    assert len(w.backend.cache) == len(actions)


def test_the_mechanism_analysis_writes_its_figure_and_tables(tmp_path, capsys):
    import csv

    from overhang_framework.analyses.ipe_mechanism import main

    main(["--out", str(tmp_path), "--quick", "--no-progress"])
    wrote = capsys.readouterr().out.strip().splitlines()[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "ipe_mechanism.csv", "ipe_mechanism.json", "ipe_mechanism.png", "ipe_mechanism_towers.csv"]
    assert all(str(p) in wrote for p in tmp_path.iterdir())
    assert (tmp_path / "ipe_mechanism.png").read_bytes()[:4] == b"\x89PNG"
    rows = list(csv.DictReader(open(tmp_path / "ipe_mechanism.csv")))
    assert {(float(r["sigma"]), int(r["n_blocks"])) for r in rows} == {
        (s, n) for s in (0.0, 0.03, 0.1) for n in range(2, 8)}
    by = {(float(r["sigma"]), int(r["n_blocks"])): r for r in rows}
    assert all(float(by[0.0, n]["entropy"]) == 0 and float(by[0.0, n]["accuracy"]) == 1 for n in range(2, 8))
    mean_h = {s: np.mean([float(by[s, n]["entropy"]) for n in range(2, 8)]) for s in (0.03, 0.1)}
    assert 0 < mean_h[0.03] < mean_h[0.1]
    assert not list(tmp_path.glob(".*.tmp")) and not list(tmp_path.glob(".*.png"))
