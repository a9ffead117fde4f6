"""Static-equilibrium physics: a tower stands if its blocks can be in equilibrium.

Every block is a rigid ``width x BLOCK_HEIGHT`` rectangle of uniform density
(mass proportional to its width). Blocks touch through *contacts*:

* bottom contacts: a block of layer ``L`` rests on every block of layer ``L-1``
  whose x interval overlaps its own by more than ``min_contact``; blocks of
  layer 0 rest on the ground. The contact is the overlap segment.
* side contacts (``side_contacts=True``): two blocks of one layer whose facing
  sides are less than ``side_gap`` apart, or overlap by at most
  ``side_overlap`` (position noise), touch along their vertical faces.
  Blocks of one layer overlapping by more than ``side_overlap`` are
  interpenetrating: the tower is reported unstable, as the reference engine
  pushes such blocks apart.

The tower is stable when there are contact forces that are compressive, lie in
the friction cone (coefficient ``mu_a * mu_b`` for blocks a, b by default, as
Bullet combines frictions; ``mu_a * ground_friction`` on the ground) and
balance every block's weight in force and torque. The *safety margin* shrinks
every contact segment by ``margin`` at both ends (a segment shorter than
``2 * margin`` becomes a point at its middle), so a block whose load passes
within ``margin`` of an edge counts as tipping. A negative margin widens every
segment by ``-margin`` at both ends (a lenient model, used to prove falls).

Two corrections bring the rigid model closer to the reference engine, whose
contacts are compliant: ``height_margin`` shrinks the contact under a block by
a further ``height_margin`` times the height of the centre of mass of that
block and everything resting on it (directly or not) above the contact, so a
tall load tips earlier, as it does in the engine; and ``friction_scale``
multiplies every combined friction coefficient (the engine lets blocks slip
out of friction-held configurations that rigid equilibrium accepts).

Gravity is any vector ``(gx, gz)``; only its direction matters. Friction is
optional per block.

A batch is decided in stages, each exact for what it decides; only
geometries that no cheaper stage settles reach the LP:

1. *tree check* (vectorised over the batch): when every block has exactly one
   bottom contact the contact forces are statically determinate. The force on
   the contact under block ``i`` carries the weight of ``i`` and everything
   resting on it, so the check is: the weight's line of action meets the
   (shrunk) segment, and ``|gx| <= mu |gz|``. This decides such towers unless
   the check fails and side contacts could help.
2. *load paths* (sufficient): for towers where some block has several
   supports, a few trees (each block on its support of largest overlap, its
   leftmost, its rightmost) are checked the same way; an admissible one proves
   stability, since unused contacts may carry no force.
3. *cuts* (necessary): for every layer ``L``, each connected group of blocks
   at or above ``L`` must have its weight's line of action cross the plane
   ``z = L * BLOCK_HEIGHT`` within the hull of its contacts there (and within
   their friction); a failed cut proves the tower falls.
4. *LP*: the rest is one feasibility linear program per geometry, all stacked
   block-diagonally into a single sparse problem solved by HiGHS. Each contact
   gets two end points, each with a force in the friction cone spanned by two
   rays (four non-negative unknowns per contact); each block gives three
   equations (x force, z force, torque) balancing ``t`` times its weight, with
   one load factor ``0 <= t <= 1`` per geometry. The sum of load factors is
   maximised; since feasible loads form a cone, a geometry's ``t`` is 1 when it
   can stand and 0 when it cannot (stable when ``t >= 1 - lp_tolerance``).

   With ``lp_nnls`` (the default) each geometry's system is first solved by
   non-negative least squares, and a verdict is taken only with a checked
   certificate: forces that balance the weight (standing), or the Farkas vector
   the least-squares residual gives (falling). HiGHS decides what neither
   certificate settles: scenes within its tolerances of the edge. The verdicts
   are HiGHS's (tests/test_static_engine.py), at about a fifth of the cost.

The first three stages run as one compiled loop over the scenes
(:mod:`overhang_framework.physics.static_kernel`, ``compiled``, the default) or as the NumPy functions
below (``compiled=False``); both give the same verdicts.

Scenes can come as :class:`Geometry` objects (:meth:`StaticBackend.stable_batch`)
or as arrays (:meth:`StaticBackend.stable_arrays`, the IPE's path: no Python
object per scene).

:meth:`StaticBackend.stable` first tries a scalar version of the tree check,
then falls back to the batched stages. Rigid-body equilibrium is optimistic for
statically indeterminate towers (a block on several supports may "choose" its
load path, while the compliant contacts of the reference engine do not); see
docs/physics.md for how often that matters.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from overhang_framework.geometry import BLOCK_HEIGHT, Geometry
from overhang_framework.physics import check_fields


@dataclass(frozen=True)
class StaticParams:
    """Parameters of :class:`StaticBackend` (defaults calibrated against PyBullet, see docs/physics.md)."""

    margin: float = 0.001
    friction: float = 0.5
    ground_friction: float = 0.5
    friction_combine: str = "product"
    height_margin: float = 0.002
    friction_scale: float = 0.8
    gravity: float = 9.81
    min_contact: float = 1e-6
    side_contacts: bool = True
    side_gap: float = 1e-3
    side_overlap: float = 0.02
    lp_tolerance: float = 1e-6
    lp_method: str = "highs"
    lp_nnls: bool = True
    # how the cheap stages run, not what they decide: left out of the repr that keys verdict caches
    compiled: bool = field(default=True, repr=False)
    # how the LP stage's least squares run ("compiled": the systems of a contact structure built and solved
    # in compiled loops; "scipy": built in NumPy, one SciPy call per system), not what it decides: left out
    # of the repr too
    nnls: str = field(default="compiled", repr=False)

    def __post_init__(self):
        if self.friction_combine not in ("product", "min", "mean"):
            raise ValueError(f"friction_combine must be product, min or mean, not {self.friction_combine!r}")
        if self.nnls not in ("compiled", "scipy"):
            raise ValueError(f"nnls must be compiled or scipy, not {self.nnls!r}")
        if isinstance(self.margin, bool) or not isinstance(self.margin, (int, float)) or not np.isfinite(self.margin):
            raise ValueError(f"StaticParams.margin must be a finite number, got {self.margin!r}")
        check_fields(self, non_negative=("friction", "height_margin", "friction_scale", "ground_friction", "gravity", "min_contact",
                                         "side_gap", "side_overlap", "lp_tolerance"))


def _pack(geometries: Sequence[Geometry], friction, params: StaticParams):
    """``(w, x, layer, valid, mu)``: the geometries as ``(B, N)`` arrays padded to the longest (a padding
    entry has width and centre 0, layer -10 and is not valid)."""
    B = len(geometries)
    N = max(max((len(g) for g in geometries), default=0), 1)
    w = np.zeros((B, N))
    x = np.zeros((B, N))
    layer = np.full((B, N), -10, dtype=np.int64)
    mu = np.full((B, N), float(params.friction))
    valid = np.zeros((B, N), dtype=bool)
    for b, g in enumerate(geometries):
        k = len(g)
        if k:
            arr = g.as_array()
            w[b, :k], x[b, :k], layer[b, :k] = arr[:, 0], arr[:, 1], arr[:, 2]
            valid[b, :k] = True
            if friction is not None and friction[b] is not None:
                mu[b, :k] = np.asarray(friction[b], dtype=float)[:k]
    return w, x, layer, valid, mu


def _unpack(w, x, layer, friction, params: StaticParams):
    """:func:`_pack`'s arrays from ``(B, n)`` widths, centres and layers (a width of 0 pads a row)."""
    w = np.asarray(w, dtype=float)
    x = np.asarray(x, dtype=float)
    layer = np.asarray(layer, dtype=np.int64)
    if w.shape[1] == 0:
        B = w.shape[0]
        w, x, layer = np.zeros((B, 1)), np.zeros((B, 1)), np.full((B, 1), -10, dtype=np.int64)
        friction = None
    valid = w > 0
    layer = np.where(valid, layer, -10)
    mu = np.full(w.shape, float(params.friction))
    if friction is not None:
        mu = np.where(valid, np.asarray(friction, dtype=float).reshape(w.shape), mu)
    return np.where(valid, w, 0.0), np.where(valid, x, 0.0), layer, valid, mu


def _unit_gravity(gravity, B: int, params: StaticParams):
    """``(g, zero_g)``: each scene's gravity as a unit vector ``(B, 2)``, and where it is zero."""
    if gravity is None:
        g = np.tile([0.0, -params.gravity], (B, 1))
    else:
        g = np.asarray(gravity, dtype=float).reshape(B, 2)
    norm = np.hypot(g[:, 0], g[:, 1])
    zero_g = norm < 1e-12
    return g / np.where(zero_g, 1.0, norm)[:, None], zero_g


def _combine(a: np.ndarray, b: np.ndarray, params: "StaticParams") -> np.ndarray:
    how, scale = params.friction_combine, params.friction_scale
    if how == "product":
        out = a * b
    elif how == "min":
        out = np.minimum(a, b)
    else:
        out = (a + b) / 2
    return out if scale == 1.0 else out * scale


class _Batch:
    """Padded arrays for a batch of geometries: ``(B, N)`` with a validity mask."""

    def __init__(self, geometries: Sequence[Geometry], gravity, friction, params: StaticParams):
        self._setup(*_pack(geometries, friction, params), gravity, params)

    @classmethod
    def from_arrays(cls, w: np.ndarray, x: np.ndarray, layer: np.ndarray, gravity, friction,
                    params: StaticParams) -> "_Batch":
        """A batch of ``(B, n)`` arrays of widths, centres and layers, without building a :class:`Geometry`
        per row; a width of 0 pads a row with fewer blocks. ``friction`` is ``(B, n)`` or ``None``."""
        return cls.padded(*_unpack(w, x, layer, friction, params), gravity, params)

    @classmethod
    def padded(cls, w, x, layer, valid, mu, gravity, params: StaticParams) -> "_Batch":
        """A batch of padded arrays as :func:`_pack` gives them."""
        bt = object.__new__(cls)
        bt._setup(w, x, layer, valid, mu, gravity, params)
        return bt

    def _setup(self, w, x, layer, valid, mu, gravity, params: StaticParams) -> None:
        B, N = w.shape
        self.B, self.N = B, N
        self.g, self.zero_g = _unit_gravity(gravity, B, params)
        self.w, self.x, self.layer, self.mu, self.valid = w, x, layer, mu, valid
        self.m = np.where(valid, w, 0.0)
        self.left, self.right = x - w / 2, x + w / 2
        self.zc = (layer + 0.5) * BLOCK_HEIGHT
        ov = np.minimum(self.right[:, :, None], self.right[:, None, :]) - np.maximum(
            self.left[:, :, None], self.left[:, None, :]
        )
        pair = valid[:, :, None] & valid[:, None, :]
        self.overlap = ov
        self.below = pair & (layer[:, :, None] == layer[:, None, :] + 1) & (ov > params.min_contact)
        same = pair & (layer[:, :, None] == layer[:, None, :]) & ~np.eye(N, dtype=bool)[None]
        self.clash = (same & (ov > params.side_overlap)).any(axis=(1, 2))
        if params.side_contacts:
            self.side = same & (ov >= -params.side_gap) & (x[:, :, None] < x[:, None, :])
        else:
            self.side = np.zeros_like(same)
        self.ground = valid & (layer == 0)
        self.cmargin = self._contact_margins(params)

    def _contact_margins(self, params: "StaticParams"):
        """The margin of the contacts under each block, ``(B, N)``, or the scalar ``margin``."""
        if params.height_margin == 0:
            return params.margin
        reach = _reach(self.below)
        mass = reach @ self.m[:, :, None]
        height = (reach @ (self.m * self.zc)[:, :, None]) / np.where(mass > 0, mass, 1.0)
        above = np.maximum(height[:, :, 0] - self.layer * BLOCK_HEIGHT, 0.0)
        return params.margin + params.height_margin * np.where(self.valid, above, 0.0)

    def subset(self, rows: np.ndarray) -> "_Batch":
        """The geometries ``rows`` of this batch, as a new batch sharing no state."""
        sub = object.__new__(_Batch)
        sub.B, sub.N = int(rows.size), self.N
        sub.cmargin = self.cmargin
        for k, v in vars(self).items():
            if isinstance(v, np.ndarray):
                setattr(sub, k, v[rows])
        return sub


def _distinct(flags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` of the distinct rows of ``flags`` (rows x columns, boolean or integer):
    ``flags[first]`` are the distinct rows and ``flags[first][inverse]`` is ``flags``."""
    B = flags.shape[0]
    if B < 2:
        return np.arange(B), np.arange(B)
    packed = np.ascontiguousarray(np.packbits(flags, axis=1) if flags.dtype == bool else flags)
    rows = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def _reach(below: np.ndarray) -> np.ndarray:
    """``reach[b, i, k]``: 1.0 where block ``k`` is block ``i`` or rests on it, directly or through others.

    ``below[b, k, i]``: ``k`` rests on ``i``. The closure is computed once per distinct contact structure (the
    perturbed scenes of one tower mostly share theirs) and given to every scene that has it.
    """
    B, N = below.shape[:2]
    first, inverse = _distinct(below.reshape(B, N * N))
    up = below[first].transpose(0, 2, 1).astype(float)  # up[s, i, k]: k rests on i
    reach = np.broadcast_to(np.eye(N), up.shape).copy()
    for _ in range(N):
        nxt = np.minimum(reach + reach @ up, 1.0)
        if np.array_equal(nxt, reach):
            break
        reach = nxt
    return reach[inverse]


def _choose_parent(bt: _Batch, score: np.ndarray) -> np.ndarray:
    """For every block, the supporting block with the highest ``score`` (``-1`` on the ground)."""
    parent = np.argmax(np.where(bt.below, score, -np.inf), axis=2)
    return np.where(bt.ground | ~bt.valid, -1, parent)


def _tree_check(bt: _Batch, parent: np.ndarray, params: StaticParams) -> np.ndarray:
    """Whether the contact forces of the tree ``parent`` (each block's load on one support) are admissible.

    Exact for a statically determinate tower; for others, passing is sufficient
    for stability (unused contacts carry no force), failing proves nothing.
    """
    B, N = bt.B, bt.N
    safe_parent = np.maximum(parent, 0)
    # the tree's ancestors depend on the tree alone: found once per distinct tree
    first, inverse = _distinct(np.where(bt.valid, parent + 1, -1).astype(np.int8))
    tree, valid = parent[first], bt.valid[first]
    anc = np.zeros((first.size, N, N), dtype=bool)  # anc[s, i, j]: j is i or below i in the tree
    idx = np.arange(N)
    anc[:, idx, idx] = valid
    cur = tree
    for _ in range(N):
        has = cur >= 0
        if not has.any():
            break
        bb, ii = np.nonzero(has)
        anc[bb, ii, cur[bb, ii]] = True
        up = np.take_along_axis(tree, np.maximum(cur, 0), axis=1)
        cur = np.where(has, up, -1)
    anc = anc[inverse]
    m = bt.m
    M = np.einsum("bi,bij->bj", m, anc)
    Msafe = np.where(M > 0, M, 1.0)
    X = np.einsum("bi,bij->bj", m * bt.x, anc) / Msafe
    Z = np.einsum("bi,bij->bj", m * bt.zc, anc) / Msafe
    pl = np.take_along_axis(bt.left, safe_parent, axis=1)
    pr = np.take_along_axis(bt.right, safe_parent, axis=1)
    a = np.where(bt.ground, bt.left, np.maximum(bt.left, pl))
    c = np.where(bt.ground, bt.right, np.minimum(bt.right, pr))
    a, c = _shrink(a, c, bt.cmargin)
    zcont = bt.layer * BLOCK_HEIGHT
    gx, gz = bt.g[:, 0:1], bt.g[:, 1:2]
    pmu = np.take_along_axis(bt.mu, safe_parent, axis=1)
    mu = np.where(bt.ground, _combine(bt.mu, np.full_like(bt.mu, params.ground_friction), params),
                  _combine(bt.mu, pmu, params))
    down = gz < 0
    gzs = np.where(down, gz, -1.0)
    cop = X + (zcont - Z) * gx / gzs
    ok = down & (np.abs(gx) <= mu * np.abs(gz) + 1e-12) & (cop >= a - 1e-12) & (cop <= c + 1e-12)
    ok |= ~bt.valid
    return ok.all(axis=1) | bt.zero_g


def _tree_verdicts(bt: _Batch, params: StaticParams):
    """``(determinate, stable)``: which geometries are trees, and the tree verdict.

    For geometries that are not trees, ``stable`` is True when one of a few
    load paths (each block's load on its support of largest overlap, on its
    leftmost, on its rightmost support) is admissible, and False otherwise
    (then only the LP can decide).
    """
    nsup = bt.below.sum(axis=2) + bt.ground
    is_tree = ((nsup == 1) | ~bt.valid).all(axis=1)
    supported = ((nsup >= 1) | ~bt.valid).all(axis=1)
    stable = _tree_check(bt, _choose_parent(bt, bt.overlap), params) & supported
    rest = np.flatnonzero(~is_tree & ~stable & supported)
    if rest.size:
        sub = bt.subset(rest)
        ok = np.zeros(rest.size, dtype=bool)
        for score in (-sub.x[:, None, :], sub.x[:, None, :]):
            score = np.broadcast_to(score, sub.below.shape)
            ok |= _tree_check(sub, _choose_parent(sub, score), params)
        stable[rest] = ok
    return is_tree, stable


def _cuts_pass(bt: _Batch, params: StaticParams) -> np.ndarray:
    """Necessary condition for stability, checked on horizontal cuts.

    For every layer ``L`` the blocks of layers ``>= L`` split into connected
    groups; each group is held only by its bottom contacts on the plane
    ``z = L * BLOCK_HEIGHT``, so its weight's line of action must cross that
    plane within the hull of those (shrunk) contact segments, and
    ``|gx| <= mu |gz|`` for the largest friction among them. False proves the
    geometry unstable; True proves nothing.
    """
    B, N = bt.B, bt.N
    below, valid = bt.below, bt.valid
    adj = below | below.transpose(0, 2, 1) | bt.side | bt.side.transpose(0, 2, 1)
    a = np.maximum(bt.left[:, :, None], bt.left[:, None, :])
    c = np.minimum(bt.right[:, :, None], bt.right[:, None, :])
    cm = bt.cmargin if np.isscalar(bt.cmargin) else bt.cmargin[:, :, None]
    a, c = _shrink(a, c, cm)
    mu_pair = _combine(bt.mu[:, :, None], bt.mu[:, None, :], params)
    ga, gc = _shrink(bt.left, bt.right, bt.cmargin)
    lo = np.where(bt.ground, ga, np.where(below, a, np.inf).min(axis=2))
    hi = np.where(bt.ground, gc, np.where(below, c, -np.inf).max(axis=2))
    mu_g = _combine(bt.mu, np.full_like(bt.mu, params.ground_friction), params)
    mub = np.where(bt.ground, mu_g, np.where(below, mu_pair, 0.0).max(axis=2))
    gx, gz = bt.g[:, 0:1], bt.g[:, 1:2]
    down = gz[:, 0] < 0
    ok = np.ones(B, dtype=bool)
    eye = np.eye(N, dtype=bool)[None]
    idx = np.arange(N, dtype=float)
    top = int(bt.layer[valid].max()) if valid.any() else -1
    # the groups of every cut depend on the contacts and the layers alone: found once per distinct structure
    levels = valid[:, None, :] & (bt.layer[:, None, :] >= np.arange(top + 1)[None, :, None])  # (B, cuts, N)
    first, inverse = _distinct(np.concatenate([adj.reshape(B, N * N), levels.reshape(B, -1)], axis=1))
    adj_s, levels_s = adj[first], levels[first]
    for L in range(0, top + 1):
        members_s = levels_s[:, L]
        inner = adj_s & members_s[:, :, None] & members_s[:, None, :] | (eye & members_s[:, :, None])
        label = np.where(members_s, idx[None, :], np.inf)
        for _ in range(N):
            new = np.where(inner, label[:, None, :], np.inf).min(axis=2)
            new = np.where(members_s, new, np.inf)
            if np.array_equal(new, label):
                break
            label = new
        onehot = ((label[:, :, None] == idx[None, None, :]) & members_s[:, :, None])[inverse]
        m = bt.m[:, :, None] * onehot
        M = m.sum(axis=1)
        X = (m * bt.x[:, :, None]).sum(axis=1) / np.where(M > 0, M, 1.0)
        Z = (m * bt.zc[:, :, None]).sum(axis=1) / np.where(M > 0, M, 1.0)
        base = onehot & (bt.layer == L)[:, :, None]
        hlo = np.where(base, lo[:, :, None], np.inf).min(axis=1)
        hhi = np.where(base, hi[:, :, None], -np.inf).max(axis=1)
        hmu = np.where(base, mub[:, :, None], 0.0).max(axis=1)
        gzs = np.where(gz < 0, gz, -1.0)
        cop = X + (L * BLOCK_HEIGHT - Z) * gx / gzs
        good = (cop >= hlo - 1e-12) & (cop <= hhi + 1e-12) & (np.abs(gx) <= hmu * np.abs(gz) + 1e-12)
        ok &= (good | (M <= 0)).all(axis=1)
    return (ok & down) | bt.zero_g


def _shrink(a: np.ndarray, c: np.ndarray, margin):
    """Segments ``[a, c]`` shrunk by ``margin`` (a number or an array like ``a``) at both ends, to
    their middle at most; a negative ``margin`` widens them."""
    if not np.isscalar(margin):
        mid = (a + c) / 2
        pos = margin > 0
        return np.where(pos, np.minimum(a + margin, mid), a + margin), np.where(pos, np.maximum(c - margin, mid), c - margin)
    if margin == 0:
        return a, c
    if margin < 0:
        return a + margin, c - margin
    mid = (a + c) / 2
    return np.minimum(a + margin, mid), np.maximum(c - margin, mid)


def _lp_verdicts(bt: _Batch, rows_b: np.ndarray, params: StaticParams) -> np.ndarray:
    """LP verdicts for the geometries ``rows_b`` of the batch (one stacked HiGHS solve)."""
    if rows_b.size == 0:
        return np.zeros(0, dtype=bool)
    h = BLOCK_HEIGHT
    nb = rows_b.size
    # per contact: geometry slot, body A (gets +f), body B (gets -f; -1 is the ground),
    # and the row (nx, nz, tx, tz, p1x, p1z, p2x, p2z, mu)
    s_list, A_list, Bd_list, geo = [], [], [], []
    # bottom contacts between blocks
    sb, i, j = np.nonzero(bt.below[rows_b])
    gb = rows_b[sb]
    a = np.maximum(bt.left[gb, i], bt.left[gb, j])
    c = np.minimum(bt.right[gb, i], bt.right[gb, j])
    a, c = _shrink(a, c, bt.cmargin if np.isscalar(bt.cmargin) else bt.cmargin[gb, i])
    zc = bt.layer[gb, i] * h
    mu = _combine(bt.mu[gb, i], bt.mu[gb, j], params)
    one, zero = np.ones_like(a), np.zeros_like(a)
    geo.append(np.stack([zero, one, one, zero, a, zc, c, zc, mu], axis=1))
    s_list.append(sb), A_list.append(i), Bd_list.append(j)
    # ground contacts
    sg, i = np.nonzero(bt.ground[rows_b])
    gg = rows_b[sg]
    a, c = _shrink(bt.left[gg, i], bt.right[gg, i], bt.cmargin if np.isscalar(bt.cmargin) else bt.cmargin[gg, i])
    mu = _combine(bt.mu[gg, i], np.full(i.shape, params.ground_friction), params)
    one, zero = np.ones_like(a), np.zeros_like(a)
    geo.append(np.stack([zero, one, one, zero, a, zero, c, zero, mu], axis=1))
    s_list.append(sg), A_list.append(i), Bd_list.append(np.full(i.shape, -1))
    # side contacts: A is the right block (normal +x), B the left one
    ss, i, j = np.nonzero(bt.side[rows_b])
    gs = rows_b[ss]
    xs = (bt.right[gs, i] + bt.left[gs, j]) / 2
    z0, z1 = _shrink(bt.layer[gs, i] * h, bt.layer[gs, i] * h + h, params.margin)
    mu = _combine(bt.mu[gs, i], bt.mu[gs, j], params)
    one, zero = np.ones_like(xs), np.zeros_like(xs)
    geo.append(np.stack([one, zero, zero, one, xs, z0, xs, z1, mu], axis=1))
    s_list.append(ss), A_list.append(j), Bd_list.append(i)

    S = np.concatenate(s_list)
    Abody = np.concatenate(A_list)
    Bbody = np.concatenate(Bd_list)
    G = np.concatenate(geo, axis=0)
    K = S.size
    nx, nz, tx, tz = G[:, 0], G[:, 1], G[:, 2], G[:, 3]
    P = [(G[:, 4], G[:, 5]), (G[:, 6], G[:, 7])]
    mu = G[:, 8]
    gfull = rows_b[S]
    vsub = bt.valid[rows_b]
    block_row = np.cumsum(vsub.ravel()).reshape(vsub.shape) - 1
    nrows = 3 * int(vsub.sum())
    row_of = lambda body, comp: 3 * block_row[S, body] + comp
    ri, ci, vals = [], [], []
    col = 0
    for e in range(2):
        px, pz = P[e]
        for sgn in (1.0, -1.0):
            dx, dz = nx + sgn * mu * tx, nz + sgn * mu * tz
            cols = col + np.arange(K)
            col += K
            for body, sign in ((Abody, 1.0), (Bbody, -1.0)):
                real = body >= 0
                bdy = np.maximum(body, 0)
                cx, cz = bt.x[gfull, bdy], bt.zc[gfull, bdy]
                tq = (px - cx) * dz - (pz - cz) * dx
                for comp, v in ((0, dx), (1, dz), (2, tq)):
                    ri.append(row_of(bdy, comp)[real])
                    ci.append(cols[real])
                    vals.append(sign * v[real])
    # load scale t_s per geometry: contact forces must balance t_s times the weight m * g
    # (total mass normalised to 1); the feasible loads form a cone, so max t_s is 1 or 0.
    msub = bt.m[rows_b]
    tot = msub.sum(axis=1, keepdims=True)
    mn = (msub / np.where(tot > 0, tot, 1.0))[vsub]
    slot = np.nonzero(vsub)[0]
    g = bt.g[rows_b][slot]
    brow = 3 * np.arange(slot.size)
    ri += [brow, brow + 1]
    ci += [col + slot, col + slot]
    vals += [mn * g[:, 0], mn * g[:, 1]]
    ncols = col + nb
    A = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(ri), np.concatenate(ci))), shape=(nrows, ncols)
    )
    cost = np.zeros(ncols)
    cost[col:] = -1.0
    bounds = np.zeros((ncols, 2))
    bounds[:, 1] = np.inf
    bounds[col:, 1] = 1.0
    res = linprog(cost, A_eq=A, b_eq=np.zeros(nrows), bounds=bounds, method=params.lp_method)
    if res.x is None:
        raise RuntimeError(f"HiGHS failed on the static-equilibrium LP: {res.message}")
    return res.x[col:] >= 1.0 - params.lp_tolerance


#: An LP scene stands when non-negative least squares balances it to within :data:`NNLS_STANDS` (forces
#: are in units of the tower's weight), and falls when the best balance misses by at least
#: :data:`NNLS_FALLS` and the Farkas vector it gives holds to within :data:`CERT_TOLERANCE`, relative to
#: its largest entry. Between the two, HiGHS decides at its own tolerances, as it decided every LP scene
#: before: a scene that balances to 1e-10 may be one HiGHS calls falling.
NNLS_STANDS = 1e-12
NNLS_FALLS = 1e-6
CERT_TOLERANCE = 1e-10


def _structures(bt: _Batch, rows: np.ndarray) -> list[np.ndarray]:
    """``rows`` grouped by contact structure (valid blocks, supports, side and ground contacts): the
    scenes of one group have LPs of one shape, column for column."""
    n = rows.size
    parts = np.concatenate([bt.valid[rows], bt.ground[rows], bt.below[rows].reshape(n, -1),
                            bt.side[rows].reshape(n, -1)], axis=1)
    _, gid = np.unique(np.packbits(parts, axis=1), axis=0, return_inverse=True)
    gid = gid.ravel()
    order = np.argsort(gid, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(gid[order])) + 1)


def _dense_lp(bt: _Batch, rows: np.ndarray, params: StaticParams) -> tuple[np.ndarray, np.ndarray]:
    """The force-balance systems of ``rows`` (scenes of one contact structure), as dense arrays.

    Returns ``A`` of shape ``(G, 3 * blocks, 4 * contacts)`` and ``b`` of shape ``(G, 3 * blocks)``:
    scene ``k`` stands when some ``f >= 0`` has ``A[k] f = -b[k]``. The unknowns and equations are those
    of :func:`_lp_verdicts` (two end points per contact, two friction-cone rays each; x force, z force
    and torque per block, the weight normalised to a total of 1). With ``nnls: compiled`` they are built
    by :func:`~overhang_framework.physics.static_kernel.dense_lp`, the same numbers one scene at a time.
    """
    h = BLOCK_HEIGHT
    r0 = rows[0]
    G = rows.size
    blocks = np.flatnonzero(bt.valid[r0])
    if params.nnls == "compiled":
        bi, bj = np.nonzero(bt.below[r0])
        si, sj = np.nonzero(bt.side[r0])
        cm = bt.cmargin
        scalar = np.isscalar(cm)
        return _kernel().dense_lp(np.ascontiguousarray(rows, dtype=np.int64), blocks, bi, bj,
                                  np.flatnonzero(bt.ground[r0]), si, sj, bt.left, bt.right,
                                  np.zeros((0, 0)) if scalar else cm, float(cm) if scalar else 0.0,
                                  bt.layer, bt.mu, bt.x, bt.zc, bt.m, bt.g, h, float(params.margin),
                                  float(params.ground_friction), _kernel().COMBINE[params.friction_combine],
                                  float(params.friction_scale))
    pos = np.full(bt.N, -1)
    pos[blocks] = np.arange(blocks.size)
    cm = bt.cmargin
    R = rows[:, None]
    # every contact of the structure: body A (gets +f), body B (gets -f; -1 the ground), the normal
    # (vertical for bottom and ground contacts, +x for side ones), two end points, the friction
    bi, bj = np.nonzero(bt.below[r0])
    gi = np.flatnonzero(bt.ground[r0])
    si, sj = np.nonzero(bt.side[r0])
    a, c = _shrink(np.maximum(bt.left[R, bi], bt.left[R, bj]), np.minimum(bt.right[R, bi], bt.right[R, bj]),
                   cm if np.isscalar(cm) else cm[R, bi])
    ga, gc = _shrink(bt.left[R, gi], bt.right[R, gi], cm if np.isscalar(cm) else cm[R, gi])
    xs = (bt.right[R, si] + bt.left[R, sj]) / 2
    z0, z1 = _shrink(bt.layer[R, si] * h, bt.layer[R, si] * h + h, params.margin)
    zb = bt.layer[R, bi] * h
    body_a = np.concatenate([bi, gi, sj])
    body_b = np.concatenate([bj, np.full(gi.size, -1), si])
    vertical = np.r_[np.ones(bi.size + gi.size), np.zeros(si.size)]  # normal (0, 1), tangent (1, 0); else (1, 0), (0, 1)
    ends = [(np.concatenate([a, ga, xs], axis=1), np.concatenate([zb, np.zeros_like(ga), z0], axis=1)),
            (np.concatenate([c, gc, xs], axis=1), np.concatenate([zb, np.zeros_like(gc), z1], axis=1))]
    mu = np.concatenate([_combine(bt.mu[R, bi], bt.mu[R, bj], params),
                         _combine(bt.mu[R, gi], np.full((G, gi.size), params.ground_friction), params),
                         _combine(bt.mu[R, si], bt.mu[R, sj], params)], axis=1)
    Q = body_a.size
    nx, nz = 1.0 - vertical, vertical
    tx, tz = vertical, 1.0 - vertical
    A = np.zeros((G, 3 * blocks.size, 4 * Q))
    q = np.arange(Q)
    for e, (px, pz) in enumerate(ends):
        for s_, sgn in enumerate((1.0, -1.0)):
            dx, dz = nx + sgn * mu * tx, nz + sgn * mu * tz
            col = 4 * q + 2 * e + s_
            for body, sign in ((body_a, 1.0), (body_b, -1.0)):
                on = body >= 0
                bd, cl = body[on], col[on]
                r = 3 * pos[bd]
                ddx, ddz = dx[:, on], dz[:, on]
                A[:, r, cl] = sign * ddx
                A[:, r + 1, cl] = sign * ddz
                A[:, r + 2, cl] = sign * ((px[:, on] - bt.x[R, bd]) * ddz - (pz[:, on] - bt.zc[R, bd]) * ddx)
    m = bt.m[rows][:, blocks]
    mn = m / m.sum(axis=1, keepdims=True)
    b = np.zeros((G, 3 * blocks.size))
    b[:, 0::3] = mn * bt.g[rows, 0:1]
    b[:, 1::3] = mn * bt.g[rows, 1:2]
    return A, b


def _nnls_verdicts(A: np.ndarray, b: np.ndarray, how: str = "compiled") -> np.ndarray:
    """Verdicts of the systems ``A[k] f = -b[k], f >= 0`` by non-negative least squares: 1 stands, 0 falls,
    -1 undecided.

    ``how`` solves them: ``"compiled"`` all in one compiled loop
    (:func:`~overhang_framework.physics.nnls_kernel.nnls_batch`; a system it does not finish cleanly goes to
    SciPy), ``"scipy"`` one SciPy call each. The certificates below decide either way.

    Each verdict carries a checked certificate. Standing: the least-squares forces balance the weight to
    within :data:`NNLS_STANDS`. Falling: at the least-squares optimum the residual ``r = A f + b`` has
    ``A^T r >= 0`` (zero where ``f > 0``), so ``y = -r / |r|^2`` has ``A^T y <= 0`` and ``b . y = -1``; no
    forces ``f >= 0`` can then balance the weight. That is checked to within the tolerance, and asked only
    of residuals of at least :data:`NNLS_FALLS`, beyond what HiGHS's tolerances could call balanced. With
    ``|r| >= NNLS_FALLS``, forces balancing the weight would have to total at least
    ``1 / (CERT_TOLERANCE / NNLS_FALLS)`` (10,000) times the tower's weight.
    """
    G = A.shape[0]
    A = np.ascontiguousarray(A, dtype=float)
    rhs = np.ascontiguousarray(-b, dtype=float)
    if how == "compiled":
        from overhang_framework.physics.nnls_kernel import nnls_batch

        F, done = nnls_batch(A, rhs)
        ran = np.ones(G, dtype=bool)
        todo = np.flatnonzero(~done)
    else:
        F = np.zeros((G, A.shape[2]))
        ran = np.ones(G, dtype=bool)
        todo = range(G)
    if len(todo):
        solve = _nnls_solver()
        for k in todo:
            F[k], ran[k] = solve(A[k], rhs[k])
    r = (A @ F[:, :, None])[:, :, 0] + b
    miss = np.abs(r).max(axis=1)
    y = -r / np.maximum((r * r).sum(axis=1), 1e-300)[:, None]
    worst = (A.transpose(0, 2, 1) @ y[:, :, None])[:, :, 0].max(axis=1)
    falls = (miss >= NNLS_FALLS) & (worst <= CERT_TOLERANCE * np.abs(y).max(axis=1)) & ((b * y).sum(axis=1) <= -0.5)
    out = np.where(miss <= NNLS_STANDS, 1, np.where(falls, 0, -1)).astype(np.int8)
    out[~ran] = -1
    return out


def _nnls_solver():
    """``solve(A, b) -> (f, converged)``: SciPy's NNLS, called without ``scipy.optimize.nnls``'s input checks
    (the systems are built here, finite and of the right shapes) where this SciPy has the routine."""
    try:
        from scipy.optimize._slsqplib import nnls as core
    except ImportError:
        core = None
    if core is not None:
        def solve(A, b):
            f, _, info = core(A, b, 3 * A.shape[1])
            return f, info != 3
    else:
        from scipy.optimize import nnls

        def solve(A, b):
            try:
                return nnls(A, b)[0], True
            except RuntimeError:  # iteration limit: left to HiGHS
                return np.zeros(A.shape[1]), False
    return solve


def _lp_nnls(bt: _Batch, rows_b: np.ndarray, params: StaticParams, stats: Optional[dict] = None) -> np.ndarray:
    """LP verdicts of the scenes ``rows_b``: by non-negative least squares with a checked certificate
    (:func:`_nnls_verdicts`), and by HiGHS (:func:`_lp_verdicts`) for the scenes it leaves undecided.

    ``stats`` counts ``certified`` and ``solved`` (by HiGHS) scenes.
    """
    out = np.zeros(rows_b.size, dtype=bool)
    if rows_b.size == 0:
        return out
    verdict = np.full(rows_b.size, -1, dtype=np.int8)
    for idx in _structures(bt, rows_b):
        A, b = _dense_lp(bt, rows_b[idx], params)
        verdict[idx] = _nnls_verdicts(A, b, params.nnls)
    left = np.flatnonzero(verdict < 0)
    out[:] = verdict == 1
    if left.size:
        out[left] = _lp_verdicts(bt, rows_b[left], params)
    if stats is not None:
        stats["certified"] = stats.get("certified", 0) + int(rows_b.size - left.size)
        stats["solved"] = stats.get("solved", 0) + int(left.size)
    return out


def _single_tree(geometry: Geometry, gravity, friction, params: StaticParams) -> Optional[bool]:
    """Scalar fast path for one geometry: the verdict when it is decided by the tree check alone, else None.

    Decides interpenetrating towers, zero gravity, and statically determinate
    towers (exactly as :func:`_tree_check`); everything else goes to the
    batched path.
    """
    blocks = geometry.blocks
    n = len(blocks)
    if gravity is None:
        gx, gz = 0.0, -params.gravity
    else:
        gx, gz = float(gravity[0]), float(gravity[1])
    mus = [params.friction] * n if friction is None else [float(f) for f in friction]
    parent = [-1] * n
    side = False
    for i, bi in enumerate(blocks):
        li, ri = bi.x - bi.width / 2, bi.x + bi.width / 2
        nsup = 1 if bi.layer == 0 else 0
        for j, bj in enumerate(blocks):
            if j == i:
                continue
            ov = min(ri, bj.x + bj.width / 2) - max(li, bj.x - bj.width / 2)
            if bj.layer == bi.layer:
                if ov > params.side_overlap:
                    return False
                if params.side_contacts and ov >= -params.side_gap:
                    side = True
            elif bj.layer == bi.layer - 1 and ov > params.min_contact:
                nsup += 1
                parent[i] = j
        if nsup != 1:
            return None
    if gx == 0.0 and gz == 0.0:
        return True
    if gz >= 0:
        return False
    combine = params.friction_combine
    mass = [b.width for b in blocks]
    sm = mass[:]
    sx = [m * b.x for m, b in zip(mass, blocks)]
    sz = [m * b.z for m, b in zip(mass, blocks)]
    for i in sorted(range(n), key=lambda k: -blocks[k].layer):
        p = parent[i]
        if p >= 0:
            sm[p] += sm[i]
            sx[p] += sx[i]
            sz[p] += sz[i]
    ratio = gx / gz
    margin = params.margin
    for i, b in enumerate(blocks):
        p = parent[i]
        if p < 0:
            a, c = b.x - b.width / 2, b.x + b.width / 2
            mu_b = params.ground_friction
        else:
            q = blocks[p]
            a, c = max(b.x - b.width / 2, q.x - q.width / 2), min(b.x + b.width / 2, q.x + q.width / 2)
            mu_b = mus[p]
        if combine == "product":
            mu = mus[i] * mu_b
        elif combine == "min":
            mu = min(mus[i], mu_b)
        else:
            mu = (mus[i] + mu_b) / 2
        mu *= params.friction_scale
        if params.height_margin:
            margin = params.margin + params.height_margin * max(sz[i] / sm[i] - b.layer * BLOCK_HEIGHT, 0.0)
        if margin > 0:
            mid = (a + c) / 2
            a, c = min(a + margin, mid), max(c - margin, mid)
        elif margin < 0:
            a, c = a + margin, c - margin
        cop = sx[i] / sm[i] + (b.layer * BLOCK_HEIGHT - sz[i] / sm[i]) * ratio
        if abs(gx) > mu * abs(gz) + 1e-12 or cop < a - 1e-12 or cop > c + 1e-12:
            return None if side else False
    return True


class StaticBackend:
    """:class:`~overhang_framework.physics.PhysicsBackend` deciding stability by static equilibrium."""

    name = "static"

    def __init__(self, params: Optional[StaticParams] = None, **overrides):
        base = params or StaticParams()
        self.params = StaticParams(**{**asdict(base), **overrides}) if overrides else base
        self.lp_solved = 0
        self.lp_certified = 0
        self.checked = 0

    def stable(self, geometry: Geometry, gravity: Optional[Sequence[float]] = None,
               friction: Optional[Sequence[float]] = None) -> bool:
        verdict = _single_tree(geometry, gravity, friction, self.params)
        if verdict is not None:
            self.checked += 1
            return verdict
        return bool(self.stable_batch(
            [geometry],
            None if gravity is None else np.asarray(gravity, dtype=float).reshape(1, 2),
            None if friction is None else [friction],
        )[0])

    def stable_batch(self, geometries: Sequence[Geometry], gravity: Optional[np.ndarray] = None,
                     friction: Optional[Sequence[Sequence[float]]] = None) -> np.ndarray:
        geometries = list(geometries)
        if not geometries:
            return np.zeros(0, dtype=bool)
        return self._decide(*_pack(geometries, friction, self.params), gravity)

    def stable_arrays(self, widths: np.ndarray, xs: np.ndarray, layers: np.ndarray,
                      gravity: Optional[np.ndarray] = None, friction: Optional[np.ndarray] = None) -> np.ndarray:
        """:meth:`stable_batch` for scenes given as ``(B, n)`` arrays of block widths, centres and layers
        (a width of 0 marks a padding entry), with ``gravity`` ``(B, 2)`` and ``friction`` ``(B, n)``:
        the same verdicts, without a :class:`Geometry` per scene."""
        widths = np.asarray(widths, dtype=float)
        if widths.ndim != 2 or np.shape(xs) != widths.shape or np.shape(layers) != widths.shape:
            raise ValueError(f"stable_arrays takes (scenes, blocks) arrays of one shape, got widths {widths.shape}, "
                             f"xs {np.shape(xs)} and layers {np.shape(layers)}")
        if widths.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        return self._decide(*_unpack(widths, xs, layers, friction, self.params), gravity)

    def _decide(self, w, x, layer, valid, mu, gravity) -> np.ndarray:
        """Verdicts of padded scenes (:func:`_pack`): the cheap stages, compiled (``compiled``) or in NumPy,
        then the LP for what they leave."""
        B = w.shape[0]
        if not self.params.compiled:
            return self._decide_batch(_Batch.padded(w, x, layer, valid, mu, gravity, self.params))
        p = self.params
        g, zero_g = _unit_gravity(gravity, B, p)
        code = _kernel().decide(w, x, layer, valid, mu, g, zero_g, BLOCK_HEIGHT, float(p.margin),
                                float(p.height_margin), float(p.min_contact), bool(p.side_contacts),
                                float(p.side_gap), float(p.side_overlap), float(p.ground_friction),
                                _kernel().COMBINE[p.friction_combine], float(p.friction_scale))
        stable = code == 1
        rows = np.flatnonzero(code < 0)
        if rows.size:
            grav = None if gravity is None else np.asarray(gravity, dtype=float).reshape(B, 2)[rows]
            sub = _Batch.padded(w[rows], x[rows], layer[rows], valid[rows], mu[rows], grav, p)
            stable[rows] = self._lp(sub, np.arange(rows.size))
        self.checked += B
        self.lp_solved += int(rows.size)
        return stable

    def _lp(self, bt: _Batch, rows: np.ndarray) -> np.ndarray:
        if self.params.lp_nnls:
            counts: dict = {}
            out = _lp_nnls(bt, rows, self.params, counts)
            self.lp_certified += counts["certified"]
            return out
        return _lp_verdicts(bt, rows, self.params)

    def _decide_batch(self, bt: _Batch) -> np.ndarray:
        is_tree, stable = _tree_verdicts(bt, self.params)
        has_side = bt.side.any(axis=(1, 2))
        supported = ((bt.below.sum(axis=2) + bt.ground >= 1) | ~bt.valid).all(axis=1)
        need_lp = ~bt.zero_g & ~stable & supported & (~is_tree | has_side)
        cand = np.flatnonzero(need_lp)
        if cand.size:
            need_lp[cand] = _cuts_pass(bt.subset(cand), self.params)
        need_lp &= ~bt.clash
        rows = np.flatnonzero(need_lp)
        if rows.size:
            stable[rows] = self._lp(bt, rows)
        stable &= ~bt.clash
        self.checked += bt.B
        self.lp_solved += int(rows.size)
        return stable


def _kernel():
    """The compiled stages (:mod:`overhang_framework.physics.static_kernel`), imported when first used."""
    from overhang_framework.physics import static_kernel

    return static_kernel
