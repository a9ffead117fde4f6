"""The renderers: the rasteriser draws blocks where they are, anti-aliased and mirror-exact."""

import numpy as np
import pytest

from overhang_framework.geometry import Block, Geometry
from overhang_framework.render import (
    PyBulletRenderer, RasterRenderer, block_arrays, make_renderer, to_uint8,
)

# A 16 x 16 view of x in [-4, 4], z in [0, 4.8]: a pixel is 0.5 m wide and 0.3 m high (half a layer).
SMALL = dict(size=(16, 16), x_max=4.0, z_max=4.8)


def raster(**kw):
    return RasterRenderer(**{**SMALL, **kw})


def test_a_block_covers_exactly_its_pixels():
    img = raster().render(Geometry((Block(1.0, 0.5, 0),)))  # x in [0, 1], z in [0, 0.6]
    fill = img[0]
    # columns 8 and 9 hold x in [0, 0.5] and [0.5, 1.0]; rows 14 and 15 hold z in [0.3, 0.6] and [0, 0.3]
    assert np.allclose(fill[14:16, 8:10], 1.0)
    fill[14:16, 8:10] = 0
    assert np.all(fill == 0)


def test_a_layer_is_drawn_at_its_height():
    img = raster().render(Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.0, 3))))
    rows = np.flatnonzero(img[0, :, 8] > 0)  # column 8: x in [0, 0.5]
    # layer 0 covers rows 14-15; layer 3 (z in [1.8, 2.4]) covers rows 8-9
    assert rows.tolist() == [8, 9, 14, 15]


def test_partial_coverage_is_anti_aliased():
    # x in [0.25, 1.45]: a quarter of column 8 is empty, column 10 is 0.9 covered
    img = raster().render(Geometry((Block(1.2, 0.85, 0),)))
    np.testing.assert_allclose(img[0, 15, 8:11], [0.5, 1.0, 0.9], atol=1e-6)
    # a shift by a tenth of a pixel changes the image
    moved = raster().render(Geometry((Block(1.2, 0.9, 0),)))
    assert not np.allclose(img, moved)


def test_mirrored_tower_gives_the_mirrored_image():
    g = Geometry((Block(1.8, 0.0, 0), Block(1.2, 0.73, 1), Block(0.6, 1.11, 2), Block(1.8, -0.4, 2)))
    m = Geometry(tuple(Block(b.width, -b.x, b.layer) for b in g.blocks))
    r = RasterRenderer(size=(48, 96))
    a, b = r.render(g), r.render(m)
    np.testing.assert_allclose(b, a[:, :, ::-1], atol=1e-6)
    assert not np.allclose(a, a[:, :, ::-1])


def test_the_channels_shade_the_block_from_its_centre_and_from_above():
    img = RasterRenderer(size=(24, 80), x_max=4.0, z_max=2.4).render(Geometry((Block(1.8, 0.0, 0),)))
    fill, bevel, top = img
    row = fill.shape[0] - 3
    assert bevel[row, 40] > bevel[row, 33] > 0  # brighter at the centre than near a side face
    assert top[fill.shape[0] - 6, 40] > top[fill.shape[0] - 1, 40] > 0  # brighter near the top face
    assert np.all(bevel <= fill + 1e-6) and np.all(top <= fill + 1e-6)


def test_the_coordinate_channel_is_coverage_times_position_across_the_view():
    g = Geometry((Block(1.8, 0.0, 0), Block(0.6, -1.5, 1), Block(0.6, 2.25, 1)))
    r = raster(channels=["fill", "x", "bevel"])
    img = r.render(g)
    assert r.shape == (3, 16, 16) and r.spec()["channels"] == ["fill", "x", "bevel"]
    plain = raster().render(g)
    np.testing.assert_allclose(img[0], plain[0])
    np.testing.assert_allclose(img[2], plain[1])
    centres = (np.arange(16) + 0.5) / 16  # column centres from the left edge of the view, as a fraction
    np.testing.assert_allclose(img[1], plain[0] * centres[None, :], atol=1e-6)
    # the block right of the centre is brighter than its mirror image would be: not mirror-symmetric
    assert img[1, 12, 12] > 0.7 and img[1, 12, 5] > 0 and img[1, 12, 12] > img[1, 12, 5] * 2
    assert "channels" not in raster().spec()  # the default channels: the spec older checkpoints have
    assert make_renderer(r.spec()).spec() == r.spec()
    with pytest.raises(ValueError, match="channels must be distinct names from fill, bevel, top, x"):
        raster(channels=["fill", "fill"])
    with pytest.raises(ValueError, match="unknown parameter.*channels"):
        make_renderer({"name": "pybullet", "channels": ["fill"]})


def test_batch_equals_one_by_one_and_reuses_the_buffer():
    towers = [Geometry((Block(1.2, 0.0, 0),)), Geometry((Block(1.8, 0.0, 0), Block(0.6, 0.8, 1))), Geometry()]
    r = RasterRenderer(size=(24, 48))
    out = np.full((3, *r.shape), 7.0, dtype=np.float32)
    batch = r.render_batch(towers, out=out)
    assert batch is out
    for i, g in enumerate(towers):
        np.testing.assert_allclose(batch[i], r.render(g), atol=1e-6)
    assert np.all(batch[2] == 0)
    with pytest.raises(ValueError, match="out must be a float32 array of shape"):
        r.render_batch(towers, out=np.empty((2, *r.shape), dtype=np.float32))


def test_blocks_above_the_view_are_clipped():
    img = raster(z_max=1.2).render(Geometry((Block(1.8, 0.0, 0), Block(1.8, 0.0, 1), Block(1.8, 0.0, 2))))
    assert img.shape == (3, 16, 16)
    assert np.allclose(img[0, :, 7:9], 1.0)  # the two lowest layers fill the view


def test_rendering_is_deterministic():
    g = Geometry((Block(1.8, 0.0, 0), Block(1.2, 0.337, 1)))
    r = RasterRenderer()
    assert np.array_equal(r.render(g), RasterRenderer().render(g))


def test_spec_round_trips_and_bad_specs_are_refused():
    r = RasterRenderer(size=(32, 64), z_max=3.0)
    again = make_renderer(r.spec())
    assert isinstance(again, RasterRenderer) and again.spec() == r.spec()
    with pytest.raises(ValueError, match="unknown renderer 'povray'; allowed: raster, pybullet"):
        make_renderer({"name": "povray"})
    with pytest.raises(ValueError, match="unknown parameter.*colour.*allowed"):
        make_renderer({"name": "raster", "colour": "red"})
    with pytest.raises(ValueError, match="size must be"):
        make_renderer({"name": "raster", "size": [4, 4]})
    with pytest.raises(ValueError, match="z_max must be"):
        make_renderer({"name": "raster", "z_max": -1})


def test_pybullet_renderer_draws_the_block_where_it_is():
    r = PyBulletRenderer(size=(48, 96))
    try:
        empty = r.render(Geometry())
        left = r.render(Geometry((Block(1.2, -2.0, 0),)))
        right = r.render(Geometry((Block(1.2, 2.0, 0),)))
        again = r.render(Geometry((Block(1.2, -2.0, 0),)))
    finally:
        r.close()
    assert left.shape == (3, 48, 96)
    changed_left = np.flatnonzero(np.abs(left - empty).sum(axis=(0, 1)) > 0.05)
    changed_right = np.flatnonzero(np.abs(right - empty).sum(axis=(0, 1)) > 0.05)
    assert changed_left.size and changed_right.size
    assert changed_left.max() < 48 <= changed_right.min()
    assert np.array_equal(left, again)
    assert make_renderer(r.spec()).spec() == r.spec()


def test_block_arrays_pad_and_to_uint8_converts():
    widths, xs, layers, mask = block_arrays([Geometry((Block(0.6, 0.1, 0),)), Geometry()])
    assert widths.shape == (2, 1) and mask.tolist() == [[True], [False]]
    img = to_uint8(np.ones((3, 4, 5), dtype=np.float32))
    assert img.shape == (4, 5, 3) and img.dtype == np.uint8 and img.max() == 255
