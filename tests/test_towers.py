"""Random and near-critical tower generators."""

import numpy as np
import pytest

from overhang_framework.geometry import WIDTHS
from overhang_framework.physics.static_backend import StaticBackend
from overhang_framework.rules import is_legal
from overhang_framework.physics.towers import (
    FAMILIES,
    family_towers,
    Geometry,
    episode_questions,
    find_flips,
    last_block_interval,
    near_critical_towers,
    random_towers,
    with_last_x,
)


def test_random_towers_are_seeded_legal_and_sized():
    towers = random_towers(40, seed=7)
    assert [g.key for g in towers] == [g.key for g in random_towers(40, seed=7)]
    assert [g.key for g in towers] != [g.key for g in random_towers(40, seed=8)]
    for g in towers:
        assert 2 <= len(g) <= 7
        first = g.blocks[0]
        assert first.x == 0.0 and first.layer == 0
        for k in range(1, len(g)):
            b = g.blocks[k]
            assert b.width in WIDTHS
            assert is_legal(Geometry(g.blocks[:k]), b.width, b)


def test_last_block_interval_keeps_the_block_legal():
    for g in random_towers(30, seed=3):
        lo, hi = last_block_interval(g)
        assert lo <= g.blocks[-1].x <= hi
        prefix = Geometry(g.blocks[:-1])
        w = g.blocks[-1].width
        for x in np.linspace(lo, hi, 7):
            assert is_legal(prefix, w, with_last_x(g, x).blocks[-1])


def test_flip_found_by_bisection_is_where_the_reference_changes():
    static = StaticBackend()
    towers = random_towers(30, seed=4)
    flips = find_flips(towers, static.stable_batch, tolerance=0.001)
    found = [(g, x) for g, x in zip(towers, flips) if x is not None]
    assert found
    for g, x in found:
        a, b = static.stable(with_last_x(g, x - 0.001)), static.stable(with_last_x(g, x + 0.001))
        assert a != b


def test_near_critical_towers_are_within_the_window():
    static = StaticBackend()
    crit = near_critical_towers(10, static.stable_batch, seed=1, window=0.05)
    assert len(crit) == 10
    for c in crit:
        assert abs(c.geometry.blocks[-1].x - c.flip_x) <= 0.05 + 1e-9
        assert c.geometry.blocks[:-1] == c.base.blocks[:-1]


def test_continuous_resolution_gives_off_grid_legal_towers():
    towers = random_towers(20, seed=2, resolution=None)
    xs = [b.x for g in towers for b in g.blocks[1:]]
    assert any(abs(x / 0.05 - round(x / 0.05)) > 1e-6 for x in xs)
    for g in towers:
        for k in range(1, len(g)):
            assert is_legal(Geometry(g.blocks[:k]), g.blocks[k].width, g.blocks[k])


def test_episode_questions_ask_about_one_block_on_a_standing_tower():
    static = StaticBackend()
    questions = episode_questions(static.stable_batch, per_height=12, seed=3, min_blocks=3, max_blocks=6)
    assert [q.n_blocks for q in questions] == [n for n in range(3, 7) for _ in range(12)]
    again = episode_questions(static.stable_batch, per_height=12, seed=3, min_blocks=3, max_blocks=6)
    assert [q.geometry.key for q in questions] == [q.geometry.key for q in again]
    for q in questions:
        below = q.state.geometry
        assert len(q.geometry) == q.n_blocks == len(below) + 1
        assert all(static.stable(Geometry(below.blocks[:k])) for k in range(1, len(below) + 1))
        assert is_legal(below, q.state.next_width, q.action)
        assert abs(q.action.x / 0.1 - round(q.action.x / 0.1)) < 1e-9
        assert q.stable == static.stable(q.geometry)
    assert 0 < np.mean([q.stable for q in questions]) < 1


def test_episode_questions_need_a_standing_tower_to_grow():
    with pytest.raises(RuntimeError, match="no tower of 2 blocks stands"):
        episode_questions(lambda towers: np.zeros(len(towers), dtype=bool), per_height=4, max_blocks=4)
    assert len(episode_questions(lambda towers: np.zeros(len(towers), dtype=bool), per_height=4,
                                 max_blocks=2)) == 4


@pytest.mark.parametrize("family", FAMILIES)
def test_family_towers_are_seeded_and_shaped(family):
    towers = family_towers(family, 8, seed=3)
    assert len(towers) == 8
    assert [g.key for g in towers] == [g.key for g in family_towers(family, 8, seed=3)]
    for g in towers:
        assert g.blocks[0].layer == 0 and all(b.width in WIDTHS for b in g.blocks)
    if family == "tall_cantilever":
        assert all(len(g) >= 4 and len({b.layer for b in g.blocks}) == len(g) for g in towers)
    if family == "indeterminate":
        assert all(sum(1 for b in g.blocks if b.layer == 1) == 2 for g in towers)
    if family == "edge":  # a load passes exactly through an edge: stands rigidly, tips with any margin
        exact = StaticBackend(margin=0.0, height_margin=0.0, friction_scale=1.0)
        tipped = StaticBackend(margin=1e-6, height_margin=0.0, friction_scale=1.0)
        assert all(exact.stable(g) and not tipped.stable(g) for g in towers)
