"""The com_margin predictor: the framework's predictor contract, its behaviour, and its installation.

Run after ``pip install examples/com_margin_plugin``::

    python -m pytest examples/com_margin_plugin/tests
"""

from importlib import metadata

import numpy as np
import pytest

from overhang_framework.geometry import Action, Block, Geometry
from overhang_framework.interfaces import State
from overhang_framework.plugins import Registry
from overhang_framework.testing.contracts import PredictorContract

from overhang_com_margin import ComMarginPredictor, com_margins


@pytest.fixture
def world():
    """The built-in world with static physics: fast, and enough for these tests."""
    return Registry().create("world", {"name": "overhang", "physics": "static"})


class TestComMarginContract(PredictorContract):
    @pytest.fixture
    def world(self, world):
        return world

    @pytest.fixture
    def predictor(self, world):
        return ComMarginPredictor(world)


def on_a_plank(width=1.2):
    """A 1.8 plank on a 0.6 ground block, the next block of ``width`` to place on the plank."""
    return State(Geometry((Block(0.6, 0.0, 0), Block(1.8, 0.0, 1))), (width,))


def test_a_centred_block_scores_higher_than_one_over_the_edge(world):
    p = ComMarginPredictor(world).predict(on_a_plank(), [Action(0.0, 2), Action(1.4, 2)],
                                          np.random.default_rng(0))
    assert p[0] > 0.9 > 0.1 > p[1]


def test_monotone_in_the_overhang(world):
    xs = np.round(np.arange(0.0, 1.45, 0.05), 2)
    p = ComMarginPredictor(world).predict(on_a_plank(), [Action(float(x), 2) for x in xs],
                                          np.random.default_rng(0))
    assert np.all(np.diff(p) < 0), "moving the block outwards never makes the tower safer"


def test_margin_of_a_simple_stack_by_hand():
    # a 1.2 block at x=0.5 on a 1.8 block at 0 on a 0.6 ground block at 0:
    # the plank carries mass 3.0 with its centre at 1.2*0.5/3 = 0.2, on the ground block's [-0.3, 0.3] -> 0.1;
    # the top block's centre 0.5 lies on the contact [-0.1, 0.9] -> 0.4; the ground block carries 3.6 at
    # 0.6/3.6 = 1/6 over its own [-0.3, 0.3] -> 0.1333.  The smallest is 0.1.
    m = com_margins(np.array([[0.6, 1.8, 1.2]]), np.array([[0.0, 0.0, 0.5]]), np.array([[0, 1, 2]]))
    assert m == pytest.approx([0.1])


def test_a_counterweight_on_the_far_side_restores_the_margin():
    # a plank overhanging its support is unsafe alone and safe with a weight on its other end
    # (1.8 plank at 0.7 on a 1.2 ground block: contact [-0.2, 0.6], centre 0.7 -> -0.1; a 1.2 block at 0 on
    # the plank's inner end moves the load to (1.8 * 0.7) / 3.0 = 0.42 -> 0.18)
    alone = com_margins(np.array([[1.2, 1.8]]), np.array([[0.0, 0.7]]), np.array([[0, 1]]))
    weighted = com_margins(np.array([[1.2, 1.8, 1.2]]), np.array([[0.0, 0.7, 0.0]]), np.array([[0, 1, 2]]))
    assert alone[0] == pytest.approx(-0.1) and weighted[0] == pytest.approx(0.18)


def test_a_block_on_two_supports_uses_the_hull_of_its_contacts():
    # a 1.8 bridge on two 0.6 posts at -0.6 and 0.6 on a 1.8 ground block: bridge and posts are checked
    # together (centre 0 over the hull [-0.9, 0.9] of the posts' contacts: 0.9); the bridge's own centre 0
    # lies in the hull [-0.9, 0.9] of its two contacts (0.9); the ground block's centre 0 in [-0.9, 0.9]
    m = com_margins(np.array([[1.8, 0.6, 0.6, 1.8]]), np.array([[0.0, -0.6, 0.6, 0.0]]), np.array([[0, 1, 1, 2]]))
    assert m[0] == pytest.approx(0.9)
    # move one post inwards to 0.2: the bridge's contacts span [-0.9, 0.5], 0.5 from its centre
    m = com_margins(np.array([[1.8, 0.6, 0.6, 1.8]]), np.array([[0.0, -0.6, 0.2, 0.0]]), np.array([[0, 1, 1, 2]]))
    assert m[0] == pytest.approx(0.5)


@pytest.mark.parametrize("params", [{"scale": 0}, {"scale": -1}, {"scale": "wide"}, {"bias": float("nan")}])
def test_bad_parameters_are_refused(world, params):
    with pytest.raises(ValueError):
        ComMarginPredictor(world, **params)


def _installed() -> bool:
    try:
        metadata.distribution("overhang-com-margin")
    except metadata.PackageNotFoundError:
        return False
    return True


@pytest.mark.skipif(not _installed(), reason="needs `pip install examples/com_margin_plugin` (its entry point)")
def test_installed_plugin_registers_the_predictor_and_its_config(world):
    from overhang_framework.app import build_models
    from overhang_framework.config import compose_config

    assert "com_margin" in Registry().names("predictor")
    cfg = compose_config(["predictor=com_margin", "predictor.scale=0.1", "world.physics=static"])
    predictor = build_models(cfg)["predictor"]
    assert isinstance(predictor, ComMarginPredictor) and predictor.scale == 0.1 and predictor.bias == 0.0
