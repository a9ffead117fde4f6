"""The static backend's cheap stages as one compiled loop over scenes (numba), and the LP stage's systems.

:func:`decide` gives, for each scene of a padded batch, the verdict of stages 1-3 of
:class:`~overhang_framework.physics.static_backend.StaticBackend` (tree check, load paths, cuts):
``1`` stands, ``0`` falls, ``-1`` only the LP can tell. It computes what the NumPy stages compute, in the
same order of operations, one scene at a time in fixed-size scratch arrays: no temporary ``(B, N, N)``
array per stage, no Python call per step. The NumPy stages stay (``StaticParams.compiled=False``);
tests/test_static_engine.py checks that both give the same verdicts.

:func:`dense_lp` builds (``nnls: compiled``) the LP stage's force-balance systems of one contact structure's scenes as the
NumPy function does (the same numbers, tested), one scene at a time.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: ``friction_combine`` as the kernel takes it
COMBINE = {"product": 0, "min": 1, "mean": 2}
_SLACK = 1e-12


@njit(cache=True, inline="always")
def _combine(a, b, how, scale):
    if how == 0:
        out = a * b
    elif how == 1:
        out = min(a, b)
    else:
        out = (a + b) / 2
    if scale != 1.0:
        out = out * scale
    return out


@njit(cache=True, inline="always")
def _shrink_lo(a, c, margin):
    if margin > 0:
        return min(a + margin, (a + c) / 2)
    return a + margin


@njit(cache=True, inline="always")
def _shrink_hi(a, c, margin):
    if margin > 0:
        return max(c - margin, (a + c) / 2)
    return c - margin


@njit(cache=True)
def _tree_ok(N, valid, m, x, zc, left, right, layer, ground, mu, cm, parent, gx, gz, H, gfric, how, scale,
             M, SX, SZ):
    """Whether the tree ``parent`` (each block's load on one support, -1 the ground) is admissible."""
    for j in range(N):
        M[j] = 0.0
        SX[j] = 0.0
        SZ[j] = 0.0
    for i in range(N):
        if not valid[i]:
            continue
        j = i
        while j >= 0:
            M[j] += m[i]
            SX[j] += m[i] * x[i]
            SZ[j] += m[i] * zc[i]
            j = parent[j]
    down = gz < 0
    gzs = gz if down else -1.0
    for i in range(N):
        if not valid[i]:
            continue
        p = parent[i]
        sp = max(p, 0)
        if ground[i]:
            a, c = left[i], right[i]
            mu_c = _combine(mu[i], gfric, how, scale)
        else:
            a, c = max(left[i], left[sp]), min(right[i], right[sp])
            mu_c = _combine(mu[i], mu[sp], how, scale)
        lo, hi = _shrink_lo(a, c, cm[i]), _shrink_hi(a, c, cm[i])
        Ms = M[i] if M[i] > 0 else 1.0
        X, Z = SX[i] / Ms, SZ[i] / Ms
        cop = X + (layer[i] * H - Z) * gx / gzs
        if not (down and abs(gx) <= mu_c * abs(gz) + _SLACK and cop >= lo - _SLACK and cop <= hi + _SLACK):
            return False
    return True


@njit(cache=True)
def _choose(N, valid, ground, below, score, parent):
    """Each block's support of the highest ``score[i, j]`` (the first of equals), -1 on the ground."""
    for i in range(N):
        parent[i] = -1
        if not valid[i] or ground[i]:
            continue
        best = -np.inf
        p = 0
        for j in range(N):
            if below[i, j] and score[i, j] > best:
                best = score[i, j]
                p = j
        parent[i] = p


@njit(cache=True)
def decide(w, x, layer, valid, mu, g, zero_g, H, margin, height_margin, min_contact, side_contacts, side_gap,
           side_overlap, gfric, how, scale):
    """Stages 1-3 for every scene: 1 stands, 0 falls, -1 for the LP."""
    B, N = w.shape
    code = np.zeros(B, dtype=np.int8)
    m = np.zeros(N)
    xs = np.zeros(N)
    left = np.zeros(N)
    right = np.zeros(N)
    zc = np.zeros(N)
    lay = np.zeros(N, dtype=np.int64)
    ground = np.zeros(N, dtype=np.bool_)
    ov = np.zeros((N, N))
    below = np.zeros((N, N), dtype=np.bool_)
    adj = np.zeros((N, N), dtype=np.bool_)
    reach = np.zeros((N, N), dtype=np.bool_)
    score = np.zeros((N, N))
    parent = np.zeros(N, dtype=np.int64)
    cm = np.zeros(N)
    M = np.zeros(N)
    SX = np.zeros(N)
    SZ = np.zeros(N)
    lo = np.zeros(N)
    hi = np.zeros(N)
    mub = np.zeros(N)
    label = np.zeros(N, dtype=np.int64)
    stack = np.zeros(N, dtype=np.int64)
    for b in range(B):
        vb = valid[b]
        top = -1
        for i in range(N):
            if vb[i]:
                m[i] = w[b, i]
                xs[i] = x[b, i]
                lay[i] = layer[b, i]
                top = max(top, lay[i])
            else:
                m[i] = 0.0
                xs[i] = 0.0
                lay[i] = -10
            left[i] = xs[i] - m[i] / 2
            right[i] = xs[i] + m[i] / 2
            zc[i] = (lay[i] + 0.5) * H
            ground[i] = vb[i] and lay[i] == 0
        # contacts; interpenetrating blocks of one layer make the tower fall
        clash = False
        has_side = False
        for i in range(N):
            for j in range(N):
                ov[i, j] = min(right[i], right[j]) - max(left[i], left[j])
                pair = vb[i] and vb[j]
                below[i, j] = pair and lay[i] == lay[j] + 1 and ov[i, j] > min_contact
                same = pair and lay[i] == lay[j] and i != j
                if same and ov[i, j] > side_overlap:
                    clash = True
                sd = side_contacts and same and ov[i, j] >= -side_gap and xs[i] < xs[j]
                adj[i, j] = sd
                if sd:
                    has_side = True
        if clash:
            code[b] = 0
            continue
        # supports
        supported = True
        is_tree = True
        for i in range(N):
            if not vb[i]:
                continue
            n = 1 if ground[i] else 0
            for j in range(N):
                if below[i, j]:
                    n += 1
            if n < 1:
                supported = False
            if n != 1:
                is_tree = False
        if not supported:
            code[b] = 0
            continue
        # contact margins: the height of the load each contact carries (every block resting on it)
        for i in range(N):
            cm[i] = margin
        if height_margin != 0:
            for i in range(N):
                for k in range(N):
                    reach[i, k] = i == k
            for L in range(top, -1, -1):
                for i in range(N):
                    if not (vb[i] and lay[i] == L):
                        continue
                    for k in range(N):
                        if below[k, i]:
                            for q in range(N):
                                if reach[k, q]:
                                    reach[i, q] = True
            for i in range(N):
                mass = 0.0
                mz = 0.0
                for k in range(N):
                    if reach[i, k]:
                        mass += m[k]
                        mz += m[k] * zc[k]
                height = mz / (mass if mass > 0 else 1.0)
                above = max(height - lay[i] * H, 0.0) if vb[i] else 0.0
                cm[i] = margin + height_margin * above
        gx, gz = g[b, 0], g[b, 1]
        # 1-2: the tree of largest overlaps, then of leftmost and of rightmost supports
        if zero_g[b]:
            code[b] = 1
            continue
        for i in range(N):
            for j in range(N):
                score[i, j] = ov[i, j]
        _choose(N, vb, ground, below, score, parent)
        ok = _tree_ok(N, vb, m, xs, zc, left, right, lay, ground, mu[b], cm, parent, gx, gz, H, gfric, how,
                      scale, M, SX, SZ)
        if not ok and not is_tree:
            for sgn in (-1.0, 1.0):
                for i in range(N):
                    for j in range(N):
                        score[i, j] = sgn * xs[j]
                _choose(N, vb, ground, below, score, parent)
                if _tree_ok(N, vb, m, xs, zc, left, right, lay, ground, mu[b], cm, parent, gx, gz, H, gfric,
                            how, scale, M, SX, SZ):
                    ok = True
                    break
        if ok:
            code[b] = 1
            continue
        if is_tree and not has_side:
            code[b] = 0
            continue
        # 3: every horizontal cut's connected groups must be held by their contacts on the cut
        if not gz < 0:
            code[b] = 0
            continue
        for i in range(N):
            for j in range(N):
                adj[i, j] = adj[i, j] or adj[j, i] or below[i, j] or below[j, i]
        for i in range(N):
            if ground[i]:
                lo[i] = _shrink_lo(left[i], right[i], cm[i])
                hi[i] = _shrink_hi(left[i], right[i], cm[i])
                mub[i] = _combine(mu[b, i], gfric, how, scale)
                continue
            lo[i] = np.inf
            hi[i] = -np.inf
            mub_g = 0.0
            for j in range(N):
                if below[i, j]:
                    a, c = max(left[i], left[j]), min(right[i], right[j])
                    lo[i] = min(lo[i], _shrink_lo(a, c, cm[i]))
                    hi[i] = max(hi[i], _shrink_hi(a, c, cm[i]))
                    mub_g = max(mub_g, _combine(mu[b, i], mu[b, j], how, scale))
            mub[i] = mub_g
        gzs = gz
        passed = True
        for L in range(0, top + 1):
            for i in range(N):
                label[i] = -1
            for i in range(N):
                if not (vb[i] and lay[i] >= L) or label[i] >= 0:
                    continue
                label[i] = i
                stack[0] = i
                top_s = 1
                while top_s > 0:
                    top_s -= 1
                    k = stack[top_s]
                    for q in range(N):
                        if adj[k, q] and label[q] < 0 and vb[q] and lay[q] >= L:
                            label[q] = i
                            stack[top_s] = q
                            top_s += 1
            for i in range(N):
                M[i] = 0.0
                SX[i] = 0.0
                SZ[i] = 0.0
            for i in range(N):
                if label[i] >= 0:
                    k = label[i]
                    M[k] += m[i]
                    SX[k] += m[i] * xs[i]
                    SZ[k] += m[i] * zc[i]
            for k in range(N):
                if label[k] != k or not M[k] > 0:
                    continue
                hlo = np.inf
                hhi = -np.inf
                hmu = 0.0
                for i in range(N):
                    if label[i] == k and lay[i] == L:
                        hlo = min(hlo, lo[i])
                        hhi = max(hhi, hi[i])
                        hmu = max(hmu, mub[i])
                X = SX[k] / M[k]
                Z = SZ[k] / M[k]
                cop = X + (L * H - Z) * gx / gzs
                if not (cop >= hlo - _SLACK and cop <= hhi + _SLACK and abs(gx) <= hmu * abs(gz) + _SLACK):
                    passed = False
                    break
            if not passed:
                break
        code[b] = -1 if passed else 0
    return code


@njit(cache=True)
def dense_lp(rows, blocks, bi, bj, gi, si, sj, left, right, cm, cm_scalar, layer, mu, x, zc, m, g, H, margin,
             gfric, how, scale):
    """The LP stage's force-balance systems of the scenes ``rows`` of one contact structure (the contacts
    ``bi`` on ``bj``, ``gi`` on the ground, ``si`` beside ``sj``; ``blocks`` the valid ones), as
    :func:`~overhang_framework.physics.static_backend._dense_lp` builds them in NumPy: ``A`` of shape
    ``(G, 3 * blocks, 4 * contacts)`` and ``b`` of shape ``(G, 3 * blocks)``. ``cm`` holds each block's
    contact margin, or is ignored for the scalar ``cm_scalar`` when it is empty."""
    G = rows.size
    nb = blocks.size
    N = left.shape[1]
    pos = np.full(N, -1, dtype=np.int64)
    for k in range(nb):
        pos[blocks[k]] = k
    nbot, ngr, nsd = bi.size, gi.size, si.size
    Q = nbot + ngr + nsd
    A = np.zeros((G, 3 * nb, 4 * Q))
    b = np.zeros((G, 3 * nb))
    per_block = cm.shape[0] > 0
    for t in range(G):
        R = rows[t]
        for q in range(Q):
            if q < nbot:
                i, j = bi[q], bj[q]
                lo = max(left[R, i], left[R, j])
                hi = min(right[R, i], right[R, j])
                mg = cm[R, i] if per_block else cm_scalar
                ba, bb, vert = i, j, True
                z0 = layer[R, i] * H
                z1 = z0
                mu_c = _combine(mu[R, i], mu[R, j], how, scale)
            elif q < nbot + ngr:
                i = gi[q - nbot]
                lo, hi = left[R, i], right[R, i]
                mg = cm[R, i] if per_block else cm_scalar
                ba, bb, vert = i, -1, True
                z0 = 0.0
                z1 = 0.0
                mu_c = _combine(mu[R, i], gfric, how, scale)
            else:
                i, j = si[q - nbot - ngr], sj[q - nbot - ngr]
                lo = (right[R, i] + left[R, j]) / 2
                hi = lo
                mg = 0.0
                ba, bb, vert = j, i, False
                z0 = _shrink_lo(layer[R, i] * H, layer[R, i] * H + H, margin)
                z1 = _shrink_hi(layer[R, i] * H, layer[R, i] * H + H, margin)
                mu_c = _combine(mu[R, i], mu[R, j], how, scale)
            if vert:
                a_, c_ = _shrink_lo(lo, hi, mg), _shrink_hi(lo, hi, mg)
                nx, nz, tx, tz = 0.0, 1.0, 1.0, 0.0
            else:
                a_, c_ = lo, hi
                nx, nz, tx, tz = 1.0, 0.0, 0.0, 1.0
            for e in range(2):
                px = a_ if e == 0 else c_
                pz = z0 if e == 0 else z1
                for s_ in range(2):
                    sgn = 1.0 if s_ == 0 else -1.0
                    dx = nx + sgn * mu_c * tx
                    dz = nz + sgn * mu_c * tz
                    col = 4 * q + 2 * e + s_
                    for side in range(2):
                        body = ba if side == 0 else bb
                        if body < 0:
                            continue
                        sign = 1.0 if side == 0 else -1.0
                        r = 3 * pos[body]
                        A[t, r, col] = sign * dx
                        A[t, r + 1, col] = sign * dz
                        A[t, r + 2, col] = sign * ((px - x[R, body]) * dz - (pz - zc[R, body]) * dx)
        total = 0.0
        for k in range(nb):
            total += m[R, blocks[k]]
        for k in range(nb):
            mn = m[R, blocks[k]] / total
            b[t, 3 * k] = mn * g[R, 0]
            b[t, 3 * k + 1] = mn * g[R, 1]
    return A, b
