"""The static-equilibrium backend on hand-built towers with known answers."""

import numpy as np
import pytest

from overhang_framework.geometry import Geometry
from overhang_framework.physics.static_backend import StaticBackend, StaticParams
from overhang_framework.physics.towers import random_towers


def G(*rows):
    return Geometry.from_tuples(rows)


@pytest.fixture
def static():
    return StaticBackend()


def test_block_centred_past_its_supports_edge_falls(static):
    assert not static.stable(G((0.6, 0.0, 0), (1.2, 0.35, 1)))
    assert not static.stable(G((1.8, 0.0, 0), (0.6, 1.0, 1)))


def test_block_centred_on_its_support_stands(static):
    assert static.stable(G((0.6, 0.0, 0), (1.2, 0.2, 1)))
    assert static.stable(G((1.8, 0.0, 0), (0.6, 0.8, 1), (1.2, 0.8, 2)))


def test_counterweight_holds_a_cantilever(static):
    cantilever = G((0.6, 0.0, 0), (1.8, 0.45, 1))
    assert not static.stable(cantilever)
    assert static.stable(cantilever.add(G((1.2, -0.15, 2)).blocks[0]))
    assert not static.stable(cantilever.add(G((1.2, 0.9, 2)).blocks[0]))


def test_bridge_over_two_pillars_stands_and_needs_both(static):
    pillars = G((1.8, 0.0, 0), (0.6, -0.6, 1), (0.6, 0.6, 1))
    assert static.stable(pillars.add(G((1.8, 0.0, 2)).blocks[0]))
    heavy_right = pillars.add(G((1.8, 0.0, 2)).blocks[0]).add(G((1.8, 1.6, 3)).blocks[0])
    assert not static.stable(heavy_right)


def test_tilted_gravity_with_low_friction_slides(static):
    tower = G((1.2, 0.0, 0), (0.6, 0.0, 1))
    tilt = (3.0, -9.81)
    assert not static.stable(tower, gravity=tilt, friction=[0.2, 0.2])
    assert static.stable(tower, gravity=tilt, friction=[1.0, 1.0])
    assert static.stable(tower, gravity=(0.0, -9.81), friction=[0.0, 0.0])


def test_friction_is_per_block(static):
    tower = G((1.2, 0.0, 0), (0.6, 0.0, 1))
    tilt = (1.0, -9.81)  # needs mu >= 0.102
    assert static.stable(tower, gravity=tilt, friction=[0.5, 0.5])  # 0.25 everywhere
    assert not static.stable(tower, gravity=tilt, friction=[0.5, 0.1])  # top contact 0.05


def test_tilted_gravity_tips_a_tall_narrow_stack(static):
    stack = G((0.6, 0.0, 0), (0.6, 0.0, 1), (0.6, 0.0, 2), (0.6, 0.0, 3))
    assert static.stable(stack, gravity=(1.0, -9.81), friction=[2.0] * 4)
    assert not static.stable(stack, gravity=(3.0, -9.81), friction=[2.0] * 4)


def test_gravity_scale_does_not_matter_and_its_direction_does(static):
    tower = G((0.6, 0.0, 0), (1.2, 0.2, 1))
    assert static.stable(tower, gravity=(0.0, -1.0)) == static.stable(tower, gravity=(0.0, -30.0)) is True
    assert not static.stable(tower, gravity=(0.0, 9.81))
    assert static.stable(G((0.6, 0.0, 0), (1.2, 0.35, 1)), gravity=(0.0, 0.0))


def test_margin_makes_the_check_conservative_near_the_edge():
    tower = G((0.6, 0.0, 0), (1.2, 0.295, 1))
    assert StaticBackend(margin=0.0).stable(tower)
    assert not StaticBackend(margin=0.01).stable(tower)


def test_interpenetrating_blocks_fall_small_overlaps_are_tolerated(static):
    base = G((1.8, 0.0, 0), (0.6, -0.3, 1))
    assert static.stable(base.add(G((0.6, 0.29, 1)).blocks[0]))  # overlap 0.01 from noise
    assert not static.stable(base.add(G((0.6, 0.1, 1)).blocks[0]))  # overlap 0.2


def test_side_contact_lets_a_block_lean_on_its_neighbour():
    # gravity tilted to the right (needs mu >= 0.153): the left block's own
    # contact (mu 0.1) lets it slide, but it leans on its right neighbour (mu 1.0)
    tower = G((1.8, 0.0, 0), (0.6, -0.6, 1), (1.2, 0.3, 1))
    tilt = (1.5, -9.81)
    slippery = [1.0, 0.1, 1.0]
    assert StaticBackend(side_contacts=True).stable(tower, gravity=tilt, friction=slippery)
    assert not StaticBackend(side_contacts=False).stable(tower, gravity=tilt, friction=slippery)
    assert StaticBackend(side_contacts=False).stable(tower, gravity=tilt, friction=[1.0, 0.25, 1.0])
    assert not StaticBackend(side_contacts=True).stable(tower, gravity=(-1.5, -9.81), friction=slippery)


def test_batched_equals_single_with_and_without_noise(static):
    towers = random_towers(300, seed=4)
    rng = np.random.default_rng(0)
    assert np.array_equal(static.stable_batch(towers), [static.stable(g) for g in towers])
    grav = np.c_[rng.normal(0, 1.0, len(towers)), -9.81 + rng.normal(0, 0.3, len(towers))]
    fric = [rng.uniform(0.2, 1.0, len(g)) for g in towers]
    noisy = [Geometry.from_tuples((b.width, b.x + rng.normal(0, 0.03), b.layer) for b in g) for g in towers]
    batch = static.stable_batch(noisy, grav, fric)
    assert np.array_equal(batch, [static.stable(g, grav[i], fric[i]) for i, g in enumerate(noisy)])
    assert 0 < batch.sum() < len(batch)


@pytest.mark.parametrize("params", [
    StaticParams(margin=0.005),
    StaticParams(margin=0.002, height_margin=0.01, friction_scale=0.8),
    StaticParams(margin=-0.01, side_gap=0.1),
], ids=["margin", "height-margin", "widened"])
def test_fast_paths_agree_with_the_lp_on_every_tower(params):
    from overhang_framework.physics import static_backend as sb

    towers = random_towers(300, seed=9)
    rng = np.random.default_rng(1)
    grav = np.c_[rng.normal(0, 1.0, len(towers)), -9.81 + rng.normal(0, 0.3, len(towers))]
    fric = [rng.uniform(0.2, 1.0, len(g)) for g in towers]
    backend = StaticBackend(params)
    for gv, fr in ((None, None), (grav, fric)):
        batch = sb._Batch(towers, gv, fr, params)
        lp_all = sb._lp_verdicts(batch, np.arange(len(towers)), params)
        assert np.array_equal(lp_all, backend.stable_batch(towers, gv, fr))
        single = [backend.stable(g, None if gv is None else gv[i], None if fr is None else fr[i])
                  for i, g in enumerate(towers)]
        assert np.array_equal(lp_all, single)


def test_height_margin_tips_tall_loads_earlier():
    short = G((1.8, 0.0, 0), (1.2, 0.85, 1))  # 5 cm inside the edge
    tall = G((1.8, 0.0, 0), (1.2, 0.85, 1), (1.2, 0.85, 2), (1.2, 0.85, 3), (1.2, 0.85, 4))
    plain, corrected = StaticBackend(margin=0.002), StaticBackend(margin=0.002, height_margin=0.05)
    assert plain.stable(short) and plain.stable(tall)
    assert corrected.stable(short) and not corrected.stable(tall)
    assert not corrected.stable_batch([tall])[0]


def test_friction_scale_drops_the_friction_jam():
    jam = G((0.6, 0.0, 0), (0.6, -0.54, 1), (1.8, 0.08, 2), (0.6, 0.48, 1))
    assert StaticBackend(friction_scale=1.0).stable(jam)
    assert not StaticBackend(friction_scale=0.8).stable(jam)


def test_order_of_blocks_does_not_matter(static):
    towers = random_towers(100, seed=2)
    shuffled = [Geometry(tuple(reversed(g.blocks))) for g in towers]
    assert np.array_equal(static.stable_batch(towers), static.stable_batch(shuffled))


def test_params_validate():
    with pytest.raises(ValueError):
        StaticParams(friction_combine="max")
    with pytest.raises(ValueError):
        StaticParams(margin=float("nan"))


def test_a_negative_margin_widens_the_contacts():
    tower = G((0.6, 0.0, 0), (1.2, 0.31, 1))  # the upper block's centre 1 cm past the edge
    assert not StaticBackend(margin=0.0).stable(tower)
    assert StaticBackend(margin=-0.02).stable(tower)
    assert StaticBackend(margin=-0.02).stable_batch([tower])[0]


@pytest.mark.parametrize("blocks", [3, 6, 8, 9])  # 9 x 9 contact pairs do not fit one 64-bit word
def test_the_closure_of_the_contacts_is_computed_once_per_structure_and_equals_the_direct_one(blocks):
    from overhang_framework.physics.static_backend import _reach

    rng = np.random.default_rng(blocks)
    scenes = 400
    layer = np.sort(rng.integers(0, 5, size=(scenes, blocks)), axis=1)
    below = (layer[:, :, None] == layer[:, None, :] + 1) & (rng.random((scenes, blocks, blocks)) < 0.6)
    below[scenes // 2:] = below[rng.integers(0, 5, size=scenes - scenes // 2)]  # structures shared, as in the IPE's
    # the direct closure: k reaches i when a chain of supports leads from k down to i
    direct = np.zeros((scenes, blocks, blocks))
    for s in range(scenes):
        for i in range(blocks):
            seen, todo = {i}, [i]
            while todo:
                j = todo.pop()
                for k in np.flatnonzero(below[s, :, j]):
                    if k not in seen:
                        seen.add(int(k))
                        todo.append(int(k))
            direct[s, i, sorted(seen)] = 1.0
    assert np.array_equal(_reach(below), direct)
    assert _reach(below[:1]).shape == (1, blocks, blocks) and _reach(below[:0]).shape == (0, blocks, blocks)


def test_the_cut_and_tree_checks_of_a_batch_are_each_scenes_own_when_scenes_share_their_structure():
    from overhang_framework.physics.static_backend import _Batch, _cuts_pass, _tree_verdicts

    params = StaticParams()
    towers = random_towers(60, seed=11, min_blocks=3, max_blocks=7)
    rng = np.random.default_rng(2)
    # each tower with small offsets: most copies keep the tower's contacts, some lose or gain one
    rows = [tw for tw in towers for _ in range(6)]
    n = max(len(g) for g in rows)
    arr = np.zeros((len(rows), n, 3))
    arr[:, :, 2] = -1
    for i, g in enumerate(rows):
        arr[i, :len(g)] = g.as_array()
    x = arr[:, :, 1] + np.where(arr[:, :, 0] > 0, rng.normal(0, 0.05, arr.shape[:2]), 0.0)
    grav = np.c_[rng.normal(0, 0.5, len(rows)), np.full(len(rows), -9.81)]
    bt = _Batch.from_arrays(arr[:, :, 0], x, arr[:, :, 2].astype(int), grav, None, params)
    together = _cuts_pass(bt, params)
    alone = np.array([_cuts_pass(bt.subset(np.array([i])), params)[0] for i in range(bt.B)])
    assert np.array_equal(together, alone)
    assert 0 < together.sum() < together.size  # both verdicts occur
    trees, stands = _tree_verdicts(bt, params)
    for i in range(bt.B):
        one = _tree_verdicts(bt.subset(np.array([i])), params)
        assert (trees[i], stands[i]) == (one[0][0], one[1][0]), i
    assert 0 < stands.sum() < stands.size and 0 < trees.sum() < trees.size
