"""Plain, immutable geometry of the Overhang Tower task.

A tower lives in the x-z plane. Every block has the same height
(:data:`BLOCK_HEIGHT`) and one of the :data:`WIDTHS`; its position is the x of
its centre and a discrete layer (its bottom face is at ``z = layer * BLOCK_HEIGHT``).
Layer 0 is the ground layer; only the first block of a task stands on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

BLOCK_HEIGHT = 0.6
WIDTHS = (0.6, 1.2, 1.8)
GRID_HALF_WIDTH = 4.0  # x in [-4, 4]
GRID_HEIGHT = 8.0  # z in [0, 8]
MAX_LAYER = int(round(GRID_HEIGHT / BLOCK_HEIGHT, 9)) - 1  # top layer whose block fits the grid
EPS = 1e-9  # geometric tolerance for contact and overlap lengths
KEY_DECIMALS = 6  # coordinates are rounded to this many decimals in canonical keys
#: Decimals a person's x is kept to: a logged or placed x, and one seen or moved by noise (so a log's tower is the one
#: simulated, and a hand's shifted x the one the participant would place).
X_DECIMALS = 6


class IllegalWidth(ValueError):
    """A block width outside :data:`WIDTHS`."""


def check_width(width: float) -> float:
    """Return ``width`` as one of :data:`WIDTHS`, or raise :class:`IllegalWidth`."""
    for allowed in WIDTHS:
        if abs(float(width) - allowed) < 1e-6:
            return allowed
    raise IllegalWidth(
        f"illegal block width {width!r}; allowed widths are {', '.join(map(str, WIDTHS))}"
    )


@dataclass(frozen=True, order=True)
class Block:
    """One placed block: ``width``, the ``x`` of its centre, and its ``layer``."""

    width: float
    x: float
    layer: int

    @property
    def left(self) -> float:
        return self.x - self.width / 2

    @property
    def right(self) -> float:
        return self.x + self.width / 2

    @property
    def z(self) -> float:
        """Height of the block's centre."""
        return (self.layer + 0.5) * BLOCK_HEIGHT


@dataclass(frozen=True)
class Action:
    """Where to put the next block: the ``x`` of its centre and its ``layer``."""

    x: float
    layer: int


@dataclass(frozen=True)
class Geometry:
    """The placed blocks, in placement order."""

    blocks: tuple[Block, ...] = ()

    def __len__(self) -> int:
        return len(self.blocks)

    def __iter__(self):
        return iter(self.blocks)

    def add(self, block: Block) -> "Geometry":
        return Geometry(self.blocks + (block,))

    @property
    def key(self) -> tuple:
        """Canonical, order-independent key: the sorted, rounded blocks."""
        return canonical_key(self.blocks)

    def as_array(self) -> np.ndarray:
        """``(n, 3)`` float array of (width, x, layer)."""
        return np.array([(b.width, b.x, b.layer) for b in self.blocks], dtype=float).reshape(-1, 3)

    @classmethod
    def from_tuples(cls, rows: Iterable[Sequence[float]]) -> "Geometry":
        return cls(tuple(Block(check_width(w), float(x), int(layer)) for w, x, layer in rows))


def _key_row(block: Block) -> tuple:
    """One block's entry in :func:`canonical_key`: width, x (rounded, ``-0.0`` made ``0.0``), layer."""
    return (round(block.width, KEY_DECIMALS), round(block.x, KEY_DECIMALS) + 0.0, int(block.layer))


def canonical_key(blocks: Iterable[Block]) -> tuple:
    """Order-independent key of a set of blocks (coordinates rounded to ``KEY_DECIMALS``)."""
    return tuple(sorted(_key_row(b) for b in blocks))


def canonical_order(blocks: Sequence[Block]) -> list[int]:
    """The indices of ``blocks`` in canonical order: bottom up, by layer, then x, then width.

    The entries are those of :func:`canonical_key` (rounded alike), taken layer first: the order in which
    a tower is built, and the order in which the search lists a state's blocks. Blocks whose rounded
    entries tie (possible only for blocks that overlap) are ordered by their exact coordinates, so any
    permutation of one list of blocks gives the same sequence of blocks.
    """
    def rank(i: int) -> tuple:
        w, x, layer = _key_row(blocks[i])
        return (layer, x, w), (blocks[i].x + 0.0, blocks[i].width)

    return sorted(range(len(blocks)), key=rank)


def overhang(geometry: Geometry) -> float:
    """Maximum lateral extension: ``max_i |x_i| + w_i / 2`` (0 for an empty geometry)."""
    if not geometry.blocks:
        return 0.0
    return max(abs(b.x) + b.width / 2 for b in geometry.blocks)


def overlap_length(a_left: float, a_right: float, b_left: float, b_right: float) -> float:
    """Length of the intersection of two intervals (0 when disjoint)."""
    return max(0.0, min(a_right, b_right) - max(a_left, b_left))


def _isotonic(y: np.ndarray) -> np.ndarray:
    """Row-wise least-squares non-decreasing fit of ``y`` (rows x m), by the max-min formula."""
    rows, m = y.shape
    csum = np.concatenate([np.zeros((rows, 1)), np.cumsum(y, axis=1)], axis=1)
    idx = np.arange(m)
    lo, hi = idx[:, None], idx[None, :]
    length = np.where(hi >= lo, hi - lo + 1, 1)
    means = (csum[:, None, 1:] - csum[:, :-1, None]) / length  # means[r, i, l] = mean(y[r, i..l])
    fit = np.empty_like(y)
    for j in range(m):
        fit[:, j] = means[:, : j + 1, j:].min(axis=2).max(axis=1)
    return fit


def separate_overlaps(xs: np.ndarray, widths: np.ndarray, layers: np.ndarray,
                      reference_x: np.ndarray) -> np.ndarray:
    """Move perturbed block centres ``xs`` (rows x n) apart where blocks of one layer overlap.

    ``widths``, ``layers`` and ``reference_x`` (the unperturbed centres) have
    one entry per column. Within each layer the blocks keep the left-to-right
    order of ``reference_x``. Rows without an overlap are returned unchanged,
    bit for bit; a row with one gets the least-squares projection onto
    non-penetration (blocks of a layer at least touching, none moved more than
    needed).
    """
    out = xs
    for layer in np.unique(layers):
        cols = np.flatnonzero(layers == layer)
        if cols.size < 2:
            continue
        cols = cols[np.argsort(reference_x[cols], kind="stable")]
        gaps = (widths[cols[:-1]] + widths[cols[1:]]) / 2
        offsets = np.concatenate([[0.0], np.cumsum(gaps)])
        y = out[:, cols] - offsets
        bad = (np.diff(y, axis=1) < 0).any(axis=1)
        if not bad.any():
            continue
        if out is xs:
            out = xs.copy()
        out[np.ix_(np.flatnonzero(bad), cols)] = _isotonic(y[bad]) + offsets
    return out
