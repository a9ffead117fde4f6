"""The fast static engine gives the reference path's verdicts: scenes as arrays against a Geometry per
scene, the compiled cheap stages against the NumPy ones, and the NNLS-certified LP stage against HiGHS, on
thousands of scenes including near-critical ones."""

import numpy as np
import pytest

from overhang_framework.physics.towers import family_towers, random_towers, with_last_x
from overhang_framework.geometry import Geometry
from overhang_framework.physics import static_backend as sb
from overhang_framework.physics.static_backend import StaticBackend, StaticParams


def _noisy(towers, copies: int, seed: int, sigma: float = 0.03):
    """``copies`` perturbed scenes of each tower (x, gravity and friction noise), as padded arrays."""
    rng = np.random.default_rng(seed)
    n = max(len(g) for g in towers)
    rows = [g.as_array() for g in towers for _ in range(copies)]
    W, X, L = np.zeros((len(rows), n)), np.zeros((len(rows), n)), np.full((len(rows), n), -1)
    for i, arr in enumerate(rows):
        k = len(arr)
        W[i, :k], X[i, :k], L[i, :k] = arr[:, 0], arr[:, 1] + sigma * rng.standard_normal(k), arr[:, 2]
    theta = sigma * rng.standard_normal(len(rows))
    grav = 9.81 * np.c_[np.sin(theta), -np.cos(theta)]
    fric = np.where(W > 0, 0.5 + sigma * rng.standard_normal(W.shape), 0.0)
    return W, X, L, grav, fric


def _geometries(W, X, L):
    return [Geometry.from_tuples((w, x, l) for w, x, l in zip(wr, xr, lr) if w > 0) for wr, xr, lr in zip(W, X, L)]


def _lp_towers():
    """Towers whose scenes reach the LP: bridges on two pillars, and random towers."""
    return family_towers("indeterminate", 60, seed=3) + random_towers(60, seed=5, min_blocks=4)


@pytest.mark.parametrize("nnls", [True, False], ids=["nnls", "highs"])
def test_arrays_give_the_verdicts_of_a_geometry_per_scene(nnls):
    W, X, L, grav, fric = _noisy(_lp_towers(), copies=15, seed=0)
    backend = StaticBackend(lp_nnls=nnls)
    arrays = backend.stable_arrays(W, X, L, grav, fric)
    objects = backend.stable_batch(_geometries(W, X, L), grav, [f[w > 0] for f, w in zip(fric, W)])
    assert len(arrays) == 1800
    assert np.array_equal(arrays, objects)
    assert 0.1 < arrays.mean() < 0.9


@pytest.mark.parametrize("params", [StaticParams(), StaticParams(margin=0.005, height_margin=0.0),
                                    StaticParams(friction_scale=0.3), StaticParams(side_contacts=False),
                                    StaticParams(friction_combine="min", margin=-0.002),
                                    StaticParams(friction_combine="mean", side_gap=0.01)],
                         ids=["default", "margin", "low-friction", "no-sides", "lenient-min", "mean-gap"])
def test_the_compiled_stages_decide_as_the_numpy_stages(params):
    towers = _lp_towers() + random_towers(150, seed=11, min_blocks=2)
    critical = _near_critical(family_towers("indeterminate", 12, seed=8), params)
    compiled, numpy_ = StaticBackend(params, compiled=True), StaticBackend(params, compiled=False)
    for sigma in (0.01, 0.05):
        W, X, L, grav, fric = _noisy(towers, copies=8, seed=2, sigma=sigma)
        fast, slow = compiled.stable_arrays(W, X, L, grav, fric), numpy_.stable_arrays(W, X, L, grav, fric)
        assert np.array_equal(fast, slow), f"{int((fast != slow).sum())} of {fast.size} verdicts differ"
        assert 0.1 < fast.mean() < 0.9
    fast, slow = compiled.stable_batch(critical), numpy_.stable_batch(critical)
    assert len(critical) > 40 and 0 < fast.sum() < len(critical)
    assert np.array_equal(fast, slow)
    # the same scenes reach the LP either way
    assert compiled.lp_solved == numpy_.lp_solved > 300


def test_the_compiled_stages_decide_interpenetration_zero_gravity_and_missing_supports():
    towers = [Geometry.from_tuples([(1.2, 0.0, 0), (0.6, 0.2, 0)]),  # two ground blocks overlapping
              Geometry.from_tuples([(1.2, 0.0, 0), (0.6, 2.0, 1)]),  # a block on nothing
              Geometry.from_tuples([(1.2, 0.0, 0), (1.8, 0.9, 1)]),  # tips to the right
              Geometry.from_tuples([(1.2, 0.0, 0), (1.8, 0.5, 1)])]
    gravity = np.array([[0.0, -9.81], [0.0, -9.81], [0.0, 0.0], [0.0, -9.81]])
    for compiled in (True, False):
        assert StaticBackend(compiled=compiled).stable_batch(towers, gravity).tolist() == [False, False, True, True]
        assert StaticBackend(compiled=compiled).stable_batch(towers).tolist() == [False, False, False, True]


def test_stable_arrays_refuses_arrays_of_different_shapes():
    with pytest.raises(ValueError, match="one shape"):
        StaticBackend().stable_arrays(np.ones((2, 3)), np.zeros((2, 2)), np.zeros((2, 3)))


def _lp_rows(bt: sb._Batch, params: StaticParams) -> np.ndarray:
    supported = ((bt.below.sum(axis=2) + bt.ground >= 1) | ~bt.valid).all(axis=1)
    return np.flatnonzero(supported & ~bt.clash)


def _near_critical(towers, params: StaticParams, offsets=(1e-3, 1e-5, 1e-7, 1e-9)):
    """Each tower with its last block moved to within ``offsets`` of where HiGHS's verdict flips
    (found by bisection along the block's x), on both sides."""
    backend = StaticBackend(params, lp_nnls=False)
    out = []
    for g in towers:
        x0 = g.blocks[-1].x
        lo, hi = x0 - 0.6, x0 + 0.6
        at = lambda x: bool(backend.stable_batch([with_last_x(g, x)])[0])
        grid = np.linspace(lo, hi, 25)
        verdicts = [at(x) for x in grid]
        flips = [i for i in range(24) if verdicts[i] != verdicts[i + 1]]
        if not flips:
            continue
        a, b = grid[flips[0]], grid[flips[0] + 1]
        va = verdicts[flips[0]]
        for _ in range(45):
            m = (a + b) / 2
            if at(m) == va:
                a = m
            else:
                b = m
        out += [with_last_x(g, (a + b) / 2 + s * d) for d in offsets for s in (-1, 1)]
    return out


@pytest.mark.parametrize("params", [StaticParams(), StaticParams(margin=0.005, height_margin=0.0),
                                    StaticParams(friction_scale=0.3)], ids=["default", "margin", "low-friction"])
def test_nnls_stage_decides_as_highs_on_thousands_of_lp_scenes(params):
    towers = _lp_towers()
    W, X, L, grav, fric = _noisy(towers, copies=25, seed=1)
    bt = sb._Batch.from_arrays(W, X, L, grav, fric, params)
    rows = _lp_rows(bt, params)
    critical = _near_critical(family_towers("indeterminate", 40, seed=8), params)
    bc = sb._Batch(critical, None, None, params)
    crows = _lp_rows(bc, params)
    assert rows.size > 2500 and crows.size > 200
    stats: dict = {}
    for batch, r in ((bt, rows), (bc, crows)):
        highs = sb._lp_verdicts(batch, r, params)
        nnls = sb._lp_nnls(batch, r, params, stats)
        assert np.array_equal(nnls, highs), f"{int((nnls != highs).sum())} of {r.size} verdicts differ"
        assert 0 < highs.sum() < r.size
    # the certificates decide nearly everything; HiGHS only what lies within its tolerance of the edge
    assert stats["certified"] >= 0.97 * (rows.size + crows.size)


def test_the_ipe_gives_the_same_predictions_on_arrays_and_objects_across_states_of_several_sizes():
    from overhang_framework.geometry import Block
    from overhang_framework.interfaces import State
    from overhang_framework.plugins import Registry

    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    states = [State(Geometry((Block(1.2, 0.0, 0),)), (1.8, 0.6)),
              State(Geometry((Block(1.8, 0.0, 0), Block(0.6, -0.6, 1), Block(0.6, 0.6, 1))), (1.8,)),
              State(Geometry((Block(1.2, 0.0, 0), Block(1.8, 0.4, 1), Block(0.6, 1.0, 2))), (1.2, 0.6))]
    requests = [(s, world.legal_actions(s)) for s in states]
    fast, reference = (Registry().create("predictor", {"name": "ipe", "K": 20, "sigma": 0.05, "scenes": path,
                                                         "backend_params": {"lp_nnls": path == "arrays"}}, world=world)
                       for path in ("arrays", "objects"))
    rngs = lambda: [np.random.default_rng([3, i]) for i in range(len(requests))]
    together = fast.predict_many(requests, rngs())
    assert [len(p) for p in together] == [len(a) for _, a in requests]
    for p, q in zip(together, reference.predict_many(requests, rngs())):
        assert np.array_equal(p, q)
    for (state, actions), p, rng in zip(requests, together, rngs()):
        assert np.array_equal(fast.predict(state, actions, rng), p)
    assert any(0 < v < 1 for p in together for v in p)


def test_scenes_without_blocks_get_the_verdict_of_empty_geometries():
    backend = StaticBackend()
    empty = np.zeros((2, 0))
    expected = backend.stable_batch([Geometry(), Geometry()])
    assert np.array_equal(backend.stable_arrays(empty, empty, empty), expected)
    assert np.array_equal(backend.stable_arrays(empty, empty, empty, None, np.zeros((2, 0))), expected)


def _lp_batches(params: StaticParams):
    """The thousands of noisy and the near-critical scenes above, as batches with their LP scenes."""
    towers = _lp_towers()
    W, X, L, grav, fric = _noisy(towers, copies=25, seed=1)
    out = []
    for batch in (sb._Batch.from_arrays(W, X, L, grav, fric, params),
                  sb._Batch(_near_critical(family_towers("indeterminate", 40, seed=8), params), None, None, params)):
        out.append((batch, _lp_rows(batch, params)))
    return out


@pytest.mark.parametrize("params", [StaticParams(), StaticParams(friction_scale=0.3)], ids=["default", "low-friction"])
def test_the_compiled_least_squares_give_scipys_verdicts_and_residuals(params):
    from dataclasses import replace

    from scipy.optimize import nnls

    from overhang_framework.physics.nnls_kernel import nnls_batch

    batches = _lp_batches(params)
    scenes = sum(rows.size for _, rows in batches)
    assert scenes > 2500
    finished, undecided = 0, {"compiled": 0, "scipy": 0}
    for batch, rows in batches:
        # the stage's verdicts: the same, whichever way its least squares are solved
        both = {how: sb._lp_nnls(batch, rows, replace(params, nnls=how)) for how in ("compiled", "scipy")}
        assert np.array_equal(both["compiled"], both["scipy"])
        for idx in sb._structures(batch, rows):
            A, b = sb._dense_lp(batch, rows[idx], params)
            codes = {how: sb._nnls_verdicts(A, b, how) for how in ("compiled", "scipy")}
            # a certificate never contradicts another; either may leave a scene to HiGHS
            decided = (codes["compiled"] >= 0) & (codes["scipy"] >= 0)
            assert np.array_equal(codes["compiled"][decided], codes["scipy"][decided])
            for how in codes:
                undecided[how] += int((codes[how] < 0).sum())
            A, rhs = np.ascontiguousarray(A), np.ascontiguousarray(-b)
            x, ok = nnls_batch(A, rhs)
            finished += int(ok.sum())
            for k in np.flatnonzero(ok)[:5]:  # the least residual is unique even where the forces are not
                assert (x[k] >= 0).all()
                best = nnls(A[k], rhs[k])[1]
                assert np.linalg.norm(A[k] @ x[k] - rhs[k]) == pytest.approx(best, abs=1e-10)
    assert finished >= 0.99 * scenes
    # no more scenes left to HiGHS than SciPy's least squares leave
    assert undecided["compiled"] <= undecided["scipy"] + 0.002 * scenes


def test_the_compiled_least_squares_solve_or_flag_random_and_dependent_systems():
    from scipy.optimize import nnls

    from overhang_framework.physics.nnls_kernel import nnls_batch

    rng = np.random.default_rng(0)
    A = rng.standard_normal((300, 12, 20))
    A[100:200, :, 5] = A[100:200, :, 4]  # a repeated column: the forces are not unique
    A[200:, :, 7] = 0.0  # a column of zeros
    b = rng.standard_normal((300, 12))
    b[:150] = np.einsum("kij,kj->ki", A[:150], np.abs(rng.standard_normal((150, 20))))  # feasible ones
    x, ok = nnls_batch(A, b)
    assert ok.mean() > 0.95
    for k in np.flatnonzero(ok):
        assert (x[k] >= 0).all()
        assert np.linalg.norm(A[k] @ x[k] - b[k]) == pytest.approx(nnls(A[k], b[k])[1], abs=1e-9)
    assert np.abs(np.einsum("kij,kj->ki", A[:150], x[:150]) - b[:150])[ok[:150]].max() < 1e-10


def test_unknown_least_squares_solver_is_refused():
    with pytest.raises(ValueError, match="nnls must be compiled or scipy, not 'lapack'"):
        StaticParams(nnls="lapack")


@pytest.mark.parametrize("params", [StaticParams(), StaticParams(margin=0.005, height_margin=0.0),
                                    StaticParams(margin=-0.002, friction_combine="min", friction_scale=1.0),
                                    StaticParams(friction_combine="mean", side_contacts=False)],
                         ids=["default", "scalar-margin", "wider-min", "mean-no-sides"])
def test_the_compiled_systems_are_the_numpy_systems(params):
    from dataclasses import replace

    numpy_params = replace(params, nnls="scipy")
    groups = 0
    for batch, rows in _lp_batches(params):
        for idx in sb._structures(batch, rows):
            A, b = sb._dense_lp(batch, rows[idx], params)
            A0, b0 = sb._dense_lp(batch, rows[idx], numpy_params)
            assert A.shape == A0.shape and b.shape == b0.shape
            np.testing.assert_array_equal(A, A0)
            np.testing.assert_array_equal(b, b0)
            groups += 1
    assert groups > 50


def test_systems_the_compiled_loop_flags_go_to_scipy(monkeypatch):
    from overhang_framework.physics import nnls_kernel

    params = StaticParams()
    (batch, rows), _ = _lp_batches(params)
    solve = nnls_kernel.nnls_batch

    def flag_every_other(A, b):  # as if the loop had not finished every other system
        x, ok = solve(A, b)
        x[::2] = -1.0
        ok[::2] = False
        return x, ok

    expected = sb._lp_nnls(batch, rows, replace_params(params, nnls="scipy"))
    monkeypatch.setattr(nnls_kernel, "nnls_batch", flag_every_other)
    for idx in sb._structures(batch, rows)[:20]:
        A, b = sb._dense_lp(batch, rows[idx], params)
        assert np.array_equal(sb._nnls_verdicts(A, b, "compiled"), sb._nnls_verdicts(A, b, "scipy"))
    assert np.array_equal(sb._lp_nnls(batch, rows, params), expected)


def replace_params(params: StaticParams, **changes) -> StaticParams:
    from dataclasses import replace

    return replace(params, **changes)
