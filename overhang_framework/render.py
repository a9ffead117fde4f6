"""Renderers: images of a tower in the x-z plane, headless and deterministic for a geometry.

Two renderers share one small interface (:class:`Renderer`):

* :class:`RasterRenderer` (``raster``) -- a NumPy rasteriser of the x-z scene,
  used to train the CNN and at inference. Every block is an axis-aligned
  rectangle, so the fraction of a pixel it covers is the product of its
  coverage of the pixel's column and of the pixel's row: the anti-aliasing
  is exact, and a block moved by a fraction of a pixel changes the image.
  The three channels are a 2.5D shading of the same coverage: the block
  (``fill``), a bevel darker towards the left and right faces (``bevel``),
  and light from above (``top``). All three are symmetric under x -> -x, so
  mirroring a geometry mirrors its image exactly (the x range is centred on
  0). ``channels`` chooses which are drawn, in order; a fourth kind, ``x``,
  is the block's coverage times the pixel's position across the view (0 at
  the left edge, 1 at the right), a coordinate channel that tells the
  network where a pixel is, as CoordConv does; it is not mirror-symmetric.
* :class:`PyBulletRenderer` (``pybullet``) -- PyBullet's ``ER_TINY_RENDERER``
  drawing the blocks as 3D boxes in a perspective view, closer to the
  paper's renders; no window and no extra dependency.

``render_batch`` returns ``(n, channels, height, width)`` float32 arrays in [0, 1],
the layout a network takes. :meth:`Renderer.spec` is a plain dict that
:func:`make_renderer` turns back into the same renderer; a CNN checkpoint
stores it, so a model is always shown the images it was trained on.
"""

from __future__ import annotations

import abc
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.geometry import BLOCK_HEIGHT, GRID_HALF_WIDTH, Block, Geometry

RENDERERS = ("raster", "pybullet")
DEFAULT_Z_MAX = 8 * BLOCK_HEIGHT  # layers 0-7: a task of up to 8 blocks fits
#: (height, width) in pixels: 4 rows per layer and 5 cm columns. Stability turns on x, and at the same
#: pixel count this trains better than 48 x 96 (docs/cnn.md, "Input size").
DEFAULT_SIZE = (32, 160)
#: What the raster renderer can draw in a channel (see :class:`RasterRenderer`).
RASTER_CHANNELS = ("fill", "bevel", "top", "x")
DEFAULT_CHANNELS = ("fill", "bevel", "top")


def _size(size) -> tuple[int, int]:
    """``(height, width)`` from an int (square) or a pair; ``ValueError`` otherwise."""
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (int(size), int(size))
    try:
        h, w = (int(v) for v in size)
        ok = all(float(v) == int(v) for v in size) and h >= 8 and w >= 8
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"size must be a whole number >= 8 or a pair [height, width] of them, got {size!r}")
    return h, w


class Renderer(abc.ABC):
    """Draws towers: ``(n, channels, height, width)`` float32 images in [0, 1]."""

    name: str = ""
    channels: int = 3

    def __init__(self, size=DEFAULT_SIZE, x_max: float = GRID_HALF_WIDTH, z_max: float = DEFAULT_Z_MAX):
        self.height, self.width = _size(size)
        for label, value in (("x_max", x_max), ("z_max", z_max)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise ValueError(f"{label} must be a number of metres > 0, got {value!r}")
        self.x_max = float(x_max)
        self.z_max = float(z_max)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.channels, self.height, self.width)

    def spec(self) -> dict:
        """Everything :func:`make_renderer` needs to build this renderer again."""
        return {"name": self.name, "size": [self.height, self.width], "x_max": self.x_max, "z_max": self.z_max}

    def render(self, geometry: Geometry) -> np.ndarray:
        """One ``(channels, height, width)`` image."""
        return self.render_batch([geometry])[0]

    @abc.abstractmethod
    def render_batch(self, geometries: Sequence[Geometry], out: Optional[np.ndarray] = None) -> np.ndarray:
        """``(n, channels, height, width)`` images, written into ``out`` when given (it must have that shape)."""

    def render_arrays(self, widths: np.ndarray, xs: np.ndarray, layers: np.ndarray, mask: np.ndarray,
                      out: Optional[np.ndarray] = None) -> np.ndarray:
        """Images of padded block arrays (see :func:`block_arrays`), the form training and inference use.
        This builds the geometries and draws them; a renderer may draw the arrays directly."""
        geometries = [Geometry(tuple(Block(float(np.round(w, 6)), float(x), int(layer))
                                     for w, x, layer, keep in zip(*row) if keep))
                      for row in zip(widths, xs, layers, mask)]
        return self.render_batch(geometries, out=out)

    def _out(self, n: int, out: Optional[np.ndarray]) -> np.ndarray:
        shape = (n, *self.shape)
        if out is None:
            return np.empty(shape, dtype=np.float32)
        if out.shape != shape or out.dtype != np.float32:
            raise ValueError(f"out must be a float32 array of shape {shape}, got {out.dtype} {out.shape}")
        return out


def block_arrays(geometries: Sequence[Geometry]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Padded ``(n, m)`` arrays of widths, x and layers, and the mask of real blocks."""
    n = len(geometries)
    m = max((len(g) for g in geometries), default=0)
    widths = np.zeros((n, m))
    xs = np.zeros((n, m))
    layers = np.zeros((n, m))
    mask = np.zeros((n, m), dtype=bool)
    for i, g in enumerate(geometries):
        k = len(g)
        if k:
            arr = g.as_array()
            widths[i, :k], xs[i, :k], layers[i, :k] = arr[:, 0], arr[:, 1], arr[:, 2]
            mask[i, :k] = True
    return widths, xs, layers, mask


class RasterRenderer(Renderer):
    """Exactly anti-aliased, 2.5D-shaded x-z images over ``x in [-x_max, x_max]``, ``z in [0, z_max]``.

    Row 0 is the top of the image; the ground is its bottom edge. Blocks
    outside the view are clipped. See the module docstring for the channels.
    """

    name = "raster"
    BEVEL = 0.5  # the bevel channel is 1 - BEVEL at a block's side faces and 1 at its centre
    TOP = 0.5  # the top channel is 1 - TOP at a block's bottom face and 1 at its top
    CHUNK = 256  # images rendered per batch of array operations

    def __init__(self, size=DEFAULT_SIZE, x_max: float = GRID_HALF_WIDTH, z_max: float = DEFAULT_Z_MAX,
                 channels: Sequence[str] = DEFAULT_CHANNELS):
        super().__init__(size, x_max, z_max)
        if isinstance(channels, str) or not hasattr(channels, "__iter__"):
            channels = [channels]
        channels = tuple(channels)
        if not channels or len(set(channels)) != len(channels) or not set(channels) <= set(RASTER_CHANNELS):
            raise ValueError(f"channels must be distinct names from {', '.join(RASTER_CHANNELS)}, "
                             f"got {list(channels)!r}")
        self.channel_names = channels
        self.channels = len(channels)
        self._col_edges = np.linspace(-self.x_max, self.x_max, self.width + 1)
        self._row_edges = np.linspace(self.z_max, 0.0, self.height + 1)  # top row first
        self._col_centres = (self._col_edges[:-1] + self._col_edges[1:]) / 2
        self._col_edges32 = self._col_edges.astype(np.float32)
        self._col_centres32 = self._col_centres.astype(np.float32)
        row_centres = (self._row_edges[:-1] + self._row_edges[1:]) / 2
        # Row coverage of every layer that reaches into the view (H, L), and the same lit from above.
        n_layers = int(np.ceil(self.z_max / BLOCK_HEIGHT - 1e-9))
        bottom = np.arange(n_layers) * BLOCK_HEIGHT
        re = self._row_edges
        rows = np.clip(np.minimum(bottom + BLOCK_HEIGHT, re[:-1, None]) - np.maximum(bottom, re[1:, None]), 0, None)
        rows /= self.z_max / self.height
        rows[rows < 1e-9] = 0.0  # edges that meet up to rounding touch, they do not overlap
        v = np.clip((row_centres[:, None] - bottom) / BLOCK_HEIGHT, 0, 1)
        self._rows = rows.astype(np.float32)
        self._lit_rows = (rows * (1.0 - self.TOP * (1 - v))).astype(np.float32)
        self._x_ramp = ((self._col_centres + self.x_max) / (2 * self.x_max)).astype(np.float32)

    def spec(self) -> dict:
        spec = super().spec()
        if self.channel_names != DEFAULT_CHANNELS:  # older checkpoints have no key: the default channels
            spec["channels"] = list(self.channel_names)
        return spec

    def render_arrays(self, widths: np.ndarray, xs: np.ndarray, layers: np.ndarray, mask: np.ndarray,
                      out: Optional[np.ndarray] = None) -> np.ndarray:
        """Images of padded block arrays (see :func:`block_arrays`); the fast path of the CNN.

        Every block of a layer covers the same rows, so an image is
        ``rows(H, L) @ columns(L, W)``: the column coverage of each layer's
        blocks (they never overlap) times the fixed row coverage of each
        layer. The column coverage of every block of a chunk of images is one
        array operation, gathered into layers by one batched product.
        """
        n, m = widths.shape
        out = self._out(n, out)
        if n > self.CHUNK:  # bounded temporaries
            for start in range(0, n, self.CHUNK):
                stop = min(n, start + self.CHUNK)
                self.render_arrays(widths[start:stop], xs[start:stop], layers[start:stop], mask[start:stop],
                                   out=out[start:stop])
            return out
        if n == 0:
            return out
        n_layers = self._rows.shape[1]
        f32 = np.float32
        keep = np.asarray(mask, dtype=bool) & (np.asarray(layers) < n_layers)
        wj = np.where(keep, widths, 1.0).astype(f32)[..., None]  # (n, m, 1)
        left = xs.astype(f32)[..., None] - wj / 2
        right = left + wj
        cov = np.minimum(right, self._col_edges32[1:]) - np.maximum(left, self._col_edges32[:-1])  # (n, m, W)
        cov = np.where((cov > 1e-6) & keep[..., None], cov * f32(self.width / (2 * self.x_max)), f32(0))
        which = ((np.asarray(layers)[..., None] == np.arange(n_layers)) & keep[..., None]).astype(f32)
        which = which.transpose(0, 2, 1)  # (n, L, m)
        fill_cols = which @ cov  # (n, L, W)
        fill = None
        for c, name in enumerate(self.channel_names):
            if name == "fill":
                out[:, c] = fill = self._rows @ fill_cols
            elif name == "bevel":
                u = np.clip((self._col_centres32 - left) / wj, 0, 1)
                bevel = cov * (1 - f32(self.BEVEL) * (2 * u - 1) ** 2)  # symmetric in u: mirror-exact
                out[:, c] = self._rows @ (which @ bevel)
            elif name == "top":
                out[:, c] = self._lit_rows @ fill_cols
            else:  # x
                out[:, c] = (self._rows @ fill_cols if fill is None else fill) * self._x_ramp
        np.clip(out, 0.0, 1.0, out=out)
        return out

    def render_batch(self, geometries: Sequence[Geometry], out: Optional[np.ndarray] = None) -> np.ndarray:
        return self.render_arrays(*block_arrays(geometries), out=out)

    def mirror_images(self, images: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
        """The images of the mirrored towers (x -> -x) from the towers' own images, without drawing them:
        ``fill``, ``bevel`` and ``top`` are mirror-symmetric, so they are the images flipped left to
        right; ``x`` is the flipped coverage times the coordinate ramp. Equal to
        :meth:`render_arrays` of the mirrored blocks up to float rounding (the CNN's mirror averaging
        draws each tower once)."""
        out = self._out(images.shape[0], out)
        coverage = None
        for c, name in enumerate(self.channel_names):
            if name != "x":
                out[:, c] = images[:, c, :, ::-1]
                continue
            if coverage is None:
                if "fill" in self.channel_names:
                    coverage = images[:, self.channel_names.index("fill"), :, ::-1]
                else:  # the coverage from the x channel itself (the ramp is > 0 at every pixel centre)
                    coverage = images[:, c, :, ::-1] / self._x_ramp[::-1]
            np.multiply(coverage, self._x_ramp, out=out[:, c])
        return out  # in [0, 1] as the images are


class PyBulletRenderer(Renderer):
    """PyBullet's ``ER_TINY_RENDERER``: the blocks as lit 3D boxes seen from the front, slightly above.

    One headless PyBullet client per renderer; the camera frames the same
    x and z range as :class:`RasterRenderer` (``depth`` is the blocks' extent
    along y). Channels are RGB.
    """

    name = "pybullet"

    def __init__(self, size=DEFAULT_SIZE, x_max: float = GRID_HALF_WIDTH, z_max: float = DEFAULT_Z_MAX,
                 depth: float = 0.6):
        super().__init__(size, x_max, z_max)
        self.depth = float(depth)
        self._client = None

    def spec(self) -> dict:
        return {**super().spec(), "depth": self.depth}

    def _connect(self):
        import pybullet as p

        if self._client is None:
            self._client = p.connect(p.DIRECT)
            cx, cz = 0.0, self.z_max / 2
            distance = 3.0 * max(self.x_max, self.z_max)
            fov = 2 * np.degrees(np.arctan(1.08 * max(self.z_max / 2, self.x_max * self.height / self.width)
                                           / distance))
            self._view = p.computeViewMatrix([cx, -distance, cz + 0.05 * distance], [cx, 0, cz], [0, 0, 1])
            self._proj = p.computeProjectionMatrixFOV(fov, self.width / self.height, 0.1, 4 * distance)
        return p

    def render_batch(self, geometries: Sequence[Geometry], out: Optional[np.ndarray] = None) -> np.ndarray:
        out = self._out(len(geometries), out)
        p = self._connect()
        cid = self._client
        for i, g in enumerate(geometries):
            p.resetSimulation(physicsClientId=cid)
            for b in g.blocks:
                half = [b.width / 2, self.depth / 2, BLOCK_HEIGHT / 2]
                shape = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=[0.85, 0.6, 0.3, 1],
                                            physicsClientId=cid)
                p.createMultiBody(0, -1, shape, [b.x, 0.0, b.z], physicsClientId=cid)
            _, _, rgba, _, _ = p.getCameraImage(self.width, self.height, self._view, self._proj,
                                                renderer=p.ER_TINY_RENDERER, lightDirection=[0.3, -1, 1],
                                                physicsClientId=cid)
            img = np.asarray(rgba, dtype=np.float32).reshape(self.height, self.width, 4)[..., :3] / 255.0
            out[i] = img.transpose(2, 0, 1)
        return out

    def close(self) -> None:
        if self._client is not None:
            import pybullet as p

            p.disconnect(self._client)
            self._client = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


def make_renderer(spec: Optional[Mapping[str, Any]] = None, **overrides) -> Renderer:
    """The renderer a spec names (``{"name": "raster", "size": [32, 160], ...}``); ``ValueError`` for an
    unknown name or parameter."""
    params = dict(spec or {"name": "raster"})
    params.update(overrides)
    name = params.pop("name", "raster")
    classes = {"raster": RasterRenderer, "pybullet": PyBulletRenderer}
    if name not in classes:
        raise ValueError(f"unknown renderer {name!r}; allowed: {', '.join(RENDERERS)}")
    allowed = {"size", "x_max", "z_max"} | ({"depth"} if name == "pybullet" else {"channels"})
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)} for renderer {name!r}; "
                         f"allowed: {', '.join(sorted(allowed))}")
    return classes[name](**params)


def to_uint8(images: np.ndarray) -> np.ndarray:
    """``(n, 3, H, W)`` or ``(3, H, W)`` floats in [0, 1] as ``(..., H, W, 3)`` uint8, for saving as PNG
    (three channels, as colours)."""
    arr = np.asarray(images)
    return np.round(np.moveaxis(arr, -3, -1) * 255).astype(np.uint8)
