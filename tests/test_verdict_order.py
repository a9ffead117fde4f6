"""A verdict is a function of the tower, not of the order its blocks are listed in.

Near-critical towers (loads exactly on a support's edge, and the benchmark's tower families with their
last block at the reference's flip) are asked with their block lists permuted: the same blocks, so the
same legal tower. The reference, the tiered physics and the static model each give one verdict per
tower, the verdict caches give it whichever order asks first, and the motion shown for a falling
tower follows the order the blocks were listed in.
"""

import hashlib
import json

import numpy as np
import pytest

pytest.importorskip("pybullet")

from overhang_framework.bench.physics import ipe_scenes
from overhang_framework.physics.towers import family_towers, find_flips, last_block_interval, with_last_x
from overhang_framework.geometry import Block, Geometry, canonical_key, canonical_order
from overhang_framework.physics.cache import CachedBackend, DiskCachedBackend, VerdictCache, verdict_key
from overhang_framework.physics.pybullet_backend import PyBulletBackend, PyBulletParams, PyBulletSimulator
from overhang_framework.physics.static_backend import StaticBackend
from overhang_framework.physics.tiered import TieredBackend
from overhang_framework.plugins import Registry

# Blocks listed top first: simulated in the listed order, this tower stands; bottom first, it falls.
TOP_FIRST = Geometry.from_tuples([(1.2, 0.9, 1), (1.8, 0.0, 0)])


def permuted(geometry: Geometry, order) -> Geometry:
    return Geometry(tuple(geometry.blocks[i] for i in order))


def orders(n: int, seed: int) -> list[tuple]:
    """The listed order, its reverse and two seeded shuffles (distinct)."""
    rng = np.random.default_rng([seed, n])
    out = [tuple(range(n)), tuple(reversed(range(n)))] + [tuple(int(i) for i in rng.permutation(n)) for _ in range(2)]
    return list(dict.fromkeys(out))


@pytest.fixture(scope="module")
def reference():
    backend = PyBulletBackend(PyBulletParams())
    yield backend
    backend.simulator.close()


@pytest.fixture(scope="module")
def edge_towers():
    """Loads passing exactly through a support's edge (the benchmark's ``edge`` family)."""
    return family_towers("edge", 12, seed=1)


@pytest.fixture(scope="module")
def flip_towers(reference):
    """Two towers of each multi-block family with the last block at, and 1 mm either side of, the reference's flip."""
    base = [g for fam in ("tall_cantilever", "counterweight", "indeterminate") for g in family_towers(fam, 2, seed=4)]
    out = []
    for g, fx in zip(base, find_flips(base, reference.stable_batch, tolerance=0.002)):
        if fx is None:
            continue
        lo, hi = last_block_interval(g)
        out += [with_last_x(g, float(np.clip(fx + d, lo, hi))) for d in (-0.001, 0.0, 0.001)]
    assert len(out) >= 9
    return out


def test_canonical_order_lists_any_permutation_of_a_tower_alike_and_bottom_up():
    tower = Geometry.from_tuples([(0.6, 0.9, 2), (1.8, 0.0, 0), (1.2, 0.9, 1), (0.6, -0.6, 1), (1.2, -0.0, 2)])
    canonical = permuted(tower, canonical_order(tower.blocks))
    assert [b.layer for b in canonical] == sorted(b.layer for b in tower)
    assert [b.x for b in canonical if b.layer == 1] == [-0.6, 0.9]
    for order in orders(len(tower), 0):
        listed = permuted(tower, order)
        assert permuted(listed, canonical_order(listed.blocks)) == canonical
        assert canonical_key(listed.blocks) == tower.key
    # entries that tie once rounded to the key's decimals keep an order set by their exact coordinates
    close = (Block(0.6, 0.1000000001, 1), Block(0.6, 0.1, 1))
    assert canonical_key(close[:1]) == canonical_key(close[1:])
    for listed in (close, close[::-1]):
        assert [listed[i].x for i in canonical_order(listed)] == [0.1, 0.1000000001]


def test_the_listed_order_decides_knife_edge_verdicts_when_the_engine_is_given_it(reference, edge_towers):
    """The towers below separate the orders: simulated as listed, some get two verdicts."""
    sim = PyBulletSimulator(PyBulletParams())
    sim._listed_order = True
    try:
        assert sim.check(TOP_FIRST).stable and not sim.check(permuted(TOP_FIRST, (1, 0))).stable
        split = [g for g in edge_towers
                 if len({sim.check(permuted(g, o)).stable for o in orders(len(g), 1)}) > 1]
    finally:
        sim.close()
    assert split  # so the next test would fail on the engine's listed order
    assert not reference.stable(TOP_FIRST)


@pytest.mark.slow
def test_pybullet_gives_one_outcome_per_tower_whatever_the_order(reference, edge_towers, flip_towers):
    towers = edge_towers + flip_towers
    verdicts = []
    for k, g in enumerate(towers):
        outcomes = {reference.simulator.check(permuted(g, o)) for o in orders(len(g), k)}
        assert len(outcomes) == 1, g  # the same verdict, displacement and steps
        verdicts.append(outcomes.pop().stable)
    assert 0 < sum(verdicts[len(edge_towers):]) < len(flip_towers)  # both verdicts occur at the flips


@pytest.mark.slow
def test_per_block_friction_and_jitters_travel_with_their_blocks(flip_towers):
    sim = PyBulletSimulator(PyBulletParams(jitters=2, jitter=0.001))
    try:
        for k, g in enumerate(flip_towers[:6]):
            friction = np.linspace(0.3, 0.7, len(g))
            outcomes = {sim.check(permuted(g, o), friction=friction[list(o)]) for o in orders(len(g), k)}
            assert len(outcomes) == 1, g
    finally:
        sim.close()


def test_the_tiered_physics_gives_one_verdict_per_tower(edge_towers, flip_towers):
    backend = TieredBackend()
    for k, g in enumerate(edge_towers + flip_towers):
        asked = [permuted(g, o) for o in orders(len(g), k)]
        assert len(set(backend.classify(asked).tolist())) == 1, g  # the static stages
        assert len(set(backend.stable_batch(asked).tolist())) == 1, g
    assert backend.counts["reference"] > 0  # the band was asked, not only the static stages
    backend.close()


@pytest.mark.parametrize("backend", [StaticBackend(), StaticBackend(margin=0.0, height_margin=0.0, friction_scale=1.0)],
                         ids=["default", "rigid-no-margin"])
def test_the_static_model_gives_one_verdict_per_tower_and_scene(backend, edge_towers, flip_towers):
    towers = edge_towers + flip_towers + family_towers("indeterminate", 40, seed=2)
    scenes, gravity, friction = ipe_scenes(towers, np.random.default_rng(3))
    rng = np.random.default_rng(4)
    exact = backend.stable_batch(towers)
    noisy = backend.stable_batch(scenes, gravity, friction)
    assert 0 < exact.sum() < len(towers) and 0 < noisy.sum() < len(scenes)
    for _ in range(4):
        perms = [rng.permutation(len(g)) for g in towers]
        assert np.array_equal(backend.stable_batch([permuted(g, p) for g, p in zip(towers, perms)]), exact)
        moved = [permuted(s, p) for s, p in zip(scenes, perms)]
        fr = [np.asarray(f)[p] for f, p in zip(friction, perms)]
        assert np.array_equal(backend.stable_batch(moved, gravity, fr), noisy)
        assert [backend.stable(s, gravity[i], fr[i]) for i, s in enumerate(moved)] == noisy.tolist()


def test_the_verdict_cache_answers_alike_whichever_order_asks_first(reference):
    listed, reverse = TOP_FIRST, permuted(TOP_FIRST, (1, 0))
    answers = []
    for first, second in ((listed, reverse), (reverse, listed)):
        cached = CachedBackend(reference, VerdictCache())
        answers += [cached.stable(first), cached.stable(second)]
        assert cached.cache.hits == 1
    assert answers == [reference.stable(listed)] * 4


def test_verdict_files_and_the_world_answer_alike_whichever_order_asks_first(tmp_path, edge_towers):
    split = [TOP_FIRST] + edge_towers[6:8]
    answers = {}
    for name, towers in (("listed", split), ("reversed", [permuted(g, tuple(reversed(range(len(g))))) for g in split])):
        disk = DiskCachedBackend(PyBulletBackend(), tmp_path / f"{name}.sqlite")
        world = Registry().create("world", {"name": "overhang", "verdict_file": str(tmp_path / f"world-{name}.sqlite")})
        answers[name] = (disk.stable_batch(towers).tolist(), [world.is_stable(g) for g in towers])
        disk.close()
        world.backend.close()
    assert answers["listed"] == answers["reversed"]
    assert answers["listed"][0] == answers["listed"][1]


def test_a_verdict_file_written_before_canonical_order_is_not_read(tmp_path, reference):
    path = tmp_path / "old.sqlite"
    disk = DiskCachedBackend(reference, path)
    old_key = hashlib.blake2b(repr(verdict_key(TOP_FIRST, None, None, disk._context)).encode(), digest_size=16).hexdigest()
    with disk._db:
        disk._db.execute("INSERT INTO verdicts VALUES (?, ?)", (old_key, 1))  # stands: the listed order's verdict
    assert not disk.stable(TOP_FIRST)
    assert disk.misses == 1


def test_motion_frames_follow_the_listed_order(edge_towers):
    sim = PyBulletSimulator(PyBulletParams())
    try:
        g = next(t for t in edge_towers if len(t) >= 3)
        base = sim.motion(g, fps=30)
        assert len(base) > 2 and base[-1] != base[0]  # it falls
        for order in orders(len(g), 2)[1:]:
            frames = sim.motion(permuted(g, order), fps=30)
            assert frames == [[frame[i] for i in order] for frame in base]
            start = [v for f in frames[0] for v in f[:2]]
            assert start == pytest.approx([v for i in order for v in (g.blocks[i].x, g.blocks[i].z)], abs=1e-4)
    finally:
        sim.close()


@pytest.mark.slow
def test_many_near_critical_towers_get_one_verdict_from_every_physics(reference):
    """Every family at its flips (5 towers each, 5 offsets within 2 mm) and 60 edge towers, four orders each."""
    base = [g for fam in ("random", "tall_cantilever", "counterweight", "indeterminate") for g in family_towers(fam, 5, seed=6)]
    towers = list(family_towers("edge", 60, seed=0))
    for g, fx in zip(base, find_flips(base, reference.stable_batch, tolerance=0.002)):
        if fx is not None:
            lo, hi = last_block_interval(g)
            towers += [with_last_x(g, float(np.clip(fx + d, lo, hi))) for d in (-0.002, -0.001, 0.0, 0.001, 0.002)]
    tiered, static = TieredBackend(), StaticBackend()
    for k, g in enumerate(towers):
        asked = [permuted(g, o) for o in orders(len(g), k)]
        assert len({reference.simulator.check(t) for t in asked}) == 1, g
        assert len(set(tiered.stable_batch(asked).tolist())) == 1, g
        assert len(set(static.stable_batch(asked).tolist())) == 1, g
    tiered.close()


def test_the_order_benchmark_compares_both_orders_and_restores_the_engine(tmp_path, capsys):
    from overhang_framework.bench.order import engine_order, main

    checks: list = []
    with engine_order(True, checks):
        assert PyBulletSimulator._listed_order
        sim = PyBulletSimulator(PyBulletParams())
        assert sim.check(TOP_FIRST).stable
        sim.close()
    assert not PyBulletSimulator._listed_order
    assert PyBulletSimulator.check.__qualname__ == "PyBulletSimulator.check"
    assert len(checks) == 1 and checks[0][0] == TOP_FIRST and checks[0][-1] is True
    assert main(["--edge", "8", "--speed", "2", "--quiet", "--out", str(tmp_path / "order.json")]) == 0
    figures = json.loads((tmp_path / "order.json").read_text())
    assert figures["permutations"]["towers_with_two_verdicts"] == {"listed": 2, "canonical": 0}
    assert figures["speed"]["stand"]["listed"] == figures["speed"]["stand"]["canonical"]
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["permutations"] == figures["permutations"] and printed["speed"]["towers"] == 2
    with pytest.raises(SystemExit):
        main(["--edge", "-1"])
    assert "--edge must be a whole number >= 0, got -1" in capsys.readouterr().err
