"""Placement rules: grid bounds, non-penetration, support; enumeration agrees with the rule."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from overhang_framework.geometry import (
    BLOCK_HEIGHT, GRID_HALF_WIDTH, MAX_LAYER, WIDTHS, Action, Block, Geometry, IllegalWidth,
    check_width, overhang,
)
from overhang_framework import rules

BASE = Geometry((Block(0.6, 0.0, 0),))


def test_max_layer_fits_the_grid():
    assert (MAX_LAYER + 1) * BLOCK_HEIGHT <= 8.0 + 1e-9 < (MAX_LAYER + 2) * BLOCK_HEIGHT


@pytest.mark.parametrize("x, layer, legal", [
    (0.0, 1, True),        # centred on the base
    (0.85, 1, True),       # 1.2 block: spans [0.25, 1.45], rests on [0.25, 0.3]
    (0.9, 1, False),       # touches the base's corner only: zero support length
    (0.0, 2, False),       # nothing in layer 1
    (0.0, 0, False),       # only the first block stands on the ground
    (3.5, 1, False),       # outside support and at the grid's edge
])
def test_single_cases(x, layer, legal):
    assert rules.is_legal(BASE, 1.2, Action(x, layer)) is legal


def test_non_penetration_and_touching():
    g = rules.place(Geometry((Block(1.8, 0.0, 0),)), 0.6, Action(-0.3, 1))
    assert not rules.is_legal(g, 0.6, Action(0.0, 1))   # overlaps by 0.3
    assert rules.is_legal(g, 0.6, Action(0.3, 1))       # touches side by side
    assert "overlaps" in rules.illegal_reason(g, 0.6, Action(-0.1, 1))


def test_grid_bounds():
    wide = Geometry((Block(1.8, 0.0, 0),))
    tower = wide
    for layer in range(1, MAX_LAYER + 1):
        tower = rules.place(tower, 1.8, Action(0.0, layer))
    assert not rules.is_legal(tower, 0.6, Action(0.0, MAX_LAYER + 1))
    assert "outside the grid" in rules.illegal_reason(BASE, 1.8, Action(GRID_HALF_WIDTH - 0.8, 1))


def test_widths_are_checked():
    assert check_width(1.2000000001) == 1.2
    with pytest.raises(IllegalWidth, match="allowed widths are 0.6, 1.2, 1.8"):
        check_width(1.0)


def test_overhang_is_max_lateral_extent():
    g = Geometry.from_tuples([(0.6, 0, 0), (1.8, -0.6, 1), (0.6, 0.2, 2)])
    assert overhang(g) == pytest.approx(1.5)
    assert overhang(Geometry()) == 0.0


@st.composite
def towers(draw):
    """Random legal towers built by the rules' own enumeration at resolution 0.1."""
    g = Geometry((Block(draw(st.sampled_from(WIDTHS)), 0.0, 0),))
    for _ in range(draw(st.integers(0, 5))):
        w = draw(st.sampled_from(WIDTHS))
        acts = rules.legal_actions(g, w, 0.1)
        g = rules.place(g, w, draw(st.sampled_from(acts)))
    return g


def brute_force_legal(g, w, x, layer):
    l, r = x - w / 2, x + w / 2
    if l < -4 - 1e-9 or r > 4 + 1e-9 or layer < 1 or layer > MAX_LAYER:
        return False
    for b in g.blocks:
        ov = min(r, b.right) - max(l, b.left)
        if b.layer == layer and ov > 1e-9:
            return False
    return any(b.layer == layer - 1 and min(r, b.right) - max(l, b.left) > 1e-9 for b in g.blocks)


@settings(max_examples=150, deadline=None)
@given(towers(), st.sampled_from(WIDTHS), st.floats(-4.5, 4.5), st.integers(-1, 8))
def test_rule_matches_brute_force(g, w, x, layer):
    assert rules.is_legal(g, w, Action(x, layer)) == brute_force_legal(g, w, x, layer)


@settings(max_examples=100, deadline=None)
@given(towers(), st.sampled_from(WIDTHS), st.sampled_from([0.05, 0.1, 0.3]))
def test_enumeration_is_exactly_the_legal_grid_points(g, w, res):
    enumerated = set(rules.legal_actions(g, w, res))
    assert all(rules.is_legal(g, w, a) for a in enumerated)
    top = max(b.layer for b in g.blocks)
    grid = rules.candidate_xs(w, res)
    expected = {Action(float(x), layer) for layer in range(0, top + 3) for x in grid
                if rules.is_legal(g, w, Action(float(x), layer))}
    assert enumerated == expected
    # placed blocks never overlap one another
    placed = [rules.place(g, w, a) for a in list(enumerated)[:5]]
    for tower in placed:
        for i, a in enumerate(tower.blocks):
            for b in tower.blocks[i + 1:]:
                if a.layer == b.layer:
                    assert min(a.right, b.right) - max(a.left, b.left) <= 1e-9


@settings(max_examples=60, deadline=None)
@given(towers(), st.sampled_from(WIDTHS), st.sampled_from([0.01, 0.1]), st.integers(0, 2**32 - 1))
def test_a_random_legal_action_is_the_draw_from_the_enumeration(g, w, res, seed):
    actions = rules.legal_actions(g, w, res)
    a, b = np.random.default_rng(seed), np.random.default_rng(seed)
    drawn = rules.random_legal_action(g, w, res, a)
    assert drawn == actions[b.integers(len(actions))]
    assert a.random() == b.random()  # the same draws were used


@settings(max_examples=60, deadline=None)
@given(towers())
def test_canonical_key_ignores_order(g):
    rev = Geometry(tuple(reversed(g.blocks)))
    assert rev.key == g.key
    shuffled = Geometry(tuple(np.random.default_rng(0).permutation(np.array(g.blocks, dtype=object))))
    assert shuffled.key == g.key
