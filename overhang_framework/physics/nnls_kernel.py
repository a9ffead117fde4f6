"""Non-negative least squares for many small dense systems in one compiled loop (numba).

The static backend's LP stage decides a scene by non-negative least squares with a checked certificate
(:func:`~overhang_framework.physics.static_backend._nnls_verdicts`). Its systems are small (three equations a
block, four unknowns a contact: 18 x 28 for a 6-block tower on 7 contacts) and many, so one call of SciPy's NNLS per system costs more in calling than in arithmetic.
:func:`nnls_batch` solves a whole batch here with the Lawson-Hanson active-set method:

* the normal equations ``A^T A`` and ``A^T b`` are formed once per system, and the Cholesky factor of the
  free (passive) columns' block grows by one row when a column is freed, so a step costs ``O(p^2)``;
  it is computed again only when a step sends columns back to zero;
* the systems of a batch share a contact structure, so each starts from the free columns the previous
  one ended with: those whose least-squares solution is positive, dropping the others until it is (a
  valid start for the method: a non-negative least-squares solution on its free columns);
* the final solution is refined once against the system itself (the residual in double precision, a
  correction from the same factor), so it balances a standing scene as exactly as a QR solve would;
* a system the method cannot finish cleanly (a nearly dependent column, the iteration limit, or an optimum
  whose conditions do not hold after refinement) is flagged, and the caller solves it with SciPy's NNLS.

The answer is a least-squares solution: the verdicts are taken from it only through the certificates of
``_nnls_verdicts``, which do not depend on how it was found.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A column is nearly dependent on the free ones when its pivot falls below this share of its squared norm.
PIVOT = 1e-12


@njit(cache=True)
def _factor(G, idx, p, L):
    """Cholesky factor of ``G[idx[:p], idx[:p]]`` into ``L``; False when a pivot is too small."""
    for i in range(p):
        for j in range(i + 1):
            s = G[idx[i], idx[j]]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not (s > PIVOT * G[idx[i], idx[i]] and s > 0.0):  # NaN fails too
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@njit(cache=True)
def _extend(G, idx, p, L):
    """Add row ``p`` (column ``idx[p]``) to the factor of the first ``p`` columns; False when it is
    nearly dependent on them."""
    c = idx[p]
    for j in range(p):
        s = G[c, idx[j]]
        for k in range(j):
            s -= L[p, k] * L[j, k]
        L[p, j] = s / L[j, j]
    s = G[c, c]
    for k in range(p):
        s -= L[p, k] * L[p, k]
    if not (s > PIVOT * G[c, c] and s > 0.0):  # NaN fails too
        return False
    L[p, p] = np.sqrt(s)
    return True


@njit(cache=True)
def _solve(L, p, rhs, y, z):
    """``z`` from ``L L^T z = rhs`` (first ``p`` entries)."""
    for i in range(p):
        s = rhs[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    for i in range(p - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, p):
            s -= L[k, i] * z[k]
        z[i] = s / L[i, i]


@njit(cache=True)
def _residual(A, b, idx, p, x, r):
    """``r = b - A x`` over the first ``p`` free columns ``idx``."""
    for k in range(A.shape[0]):
        s = b[k]
        for q in range(p):
            s -= A[k, idx[q]] * x[idx[q]]
        r[k] = s


@njit(cache=True)
def _one(A, b, x, maxiter, G, c, w, idx, free, L, r, y, z, rhs, warm, nwarm, nwarm_out):
    """Lawson-Hanson NNLS of ``A x = b`` into ``x``; False when it did not finish cleanly. The first
    ``nwarm`` entries of ``warm`` are free columns to start from, when their least-squares solution is
    positive; the free columns at the end are left there."""
    m, n = A.shape
    for i in range(n):
        for j in range(n):
            G[i, j] = 0.0
        c[i] = 0.0
        x[i] = 0.0
        free[i] = False
    for k in range(m):
        bk = b[k]
        for i in range(n):
            a = A[k, i]
            if a != 0.0:
                c[i] += a * bk
                for j in range(i, n):
                    G[i, j] += a * A[k, j]
    for i in range(n):
        for j in range(i):
            G[i, j] = G[j, i]
    scale = 0.0
    for i in range(n):
        scale = max(scale, G[i, i])
    tol = 1e-13 * max(scale, 1e-300)
    p = 0
    it = 0
    for k in range(nwarm):
        idx[k] = warm[k]
    q = nwarm
    while q > 0:
        # the warm columns whose least-squares solution is positive: drop the others until it is
        if not _factor(G, idx, q, L):
            break
        for k in range(q):
            rhs[k] = c[idx[k]]
        _solve(L, q, rhs, y, z)
        kept = 0
        for k in range(q):
            if z[k] > 0.0:
                idx[kept] = idx[k]
                kept += 1
        if kept == q:
            p = q
            for k in range(p):
                x[idx[k]] = z[k]
                free[idx[k]] = True
            break
        q = kept
    while True:
        # the gradient's most promising column still held at zero
        for i in range(n):
            s = c[i]
            for k in range(p):
                s -= G[i, idx[k]] * x[idx[k]]
            w[i] = s
        t, best = -1, tol
        for i in range(n):
            if not free[i] and w[i] > best:
                best, t = w[i], i
        if t < 0:
            break
        idx[p] = t
        if not _extend(G, idx, p, L):
            return False
        free[t] = True
        p += 1
        while True:
            it += 1
            if it > maxiter:
                return False
            for k in range(p):
                rhs[k] = c[idx[k]]
            _solve(L, p, rhs, y, z)
            ok = True
            for k in range(p):
                if z[k] <= 0.0:
                    ok = False
                    break
            if ok:
                for k in range(p):
                    x[idx[k]] = z[k]
                break
            # step towards z as far as every free column stays non-negative
            alpha = 1.0
            for k in range(p):
                if z[k] <= 0.0:
                    xk = x[idx[k]]
                    a = xk / (xk - z[k]) if xk - z[k] > 0.0 else 0.0
                    if a < alpha:
                        alpha = a
            q = 0
            for k in range(p):
                j = idx[k]
                v = x[j] + alpha * (z[k] - x[j])
                if v <= 0.0 or (z[k] <= 0.0 and (x[j] - z[k] <= 0.0 or x[j] / (x[j] - z[k]) <= alpha)):
                    x[j] = 0.0
                    free[j] = False
                else:
                    x[j] = v
                    idx[q] = j
                    q += 1
            p = q
            if not _factor(G, idx, p, L):
                return False
    # refine once against the system itself, then check the optimum's conditions
    if p:
        _residual(A, b, idx, p, x, r)
        for q in range(p):
            s = 0.0
            for k in range(m):
                s += A[k, idx[q]] * r[k]
            rhs[q] = s
        _solve(L, p, rhs, y, z)
        for q in range(p):
            x[idx[q]] += z[q]
            if x[idx[q]] <= 0.0:
                return False
    _residual(A, b, idx, p, x, r)
    for i in range(n):
        if not free[i]:
            s = 0.0
            for k in range(m):
                s += A[k, i] * r[k]
            if s > tol:
                return False
    for q in range(p):
        warm[q] = idx[q]
    nwarm_out[0] = p
    return True


@njit(cache=True)
def nnls_batch(A, b, maxiter_factor=3):
    """``(x, ok)``: for each ``k``, ``x[k] >= 0`` minimising ``|A[k] x - b[k]|``, and whether it was found
    cleanly (see the module's notes; where not, ``x[k]`` is to be found another way)."""
    K, m, n = A.shape
    x = np.zeros((K, n))
    ok = np.zeros(K, dtype=np.bool_)
    G = np.zeros((n, n))
    c = np.zeros(n)
    w = np.zeros(n)
    idx = np.zeros(n, dtype=np.int64)
    free = np.zeros(n, dtype=np.bool_)
    L = np.zeros((n, n))
    r = np.zeros(m)
    y = np.zeros(n)
    z = np.zeros(n)
    rhs = np.zeros(n)
    warm = np.zeros(n, dtype=np.int64)
    nwarm = np.zeros(1, dtype=np.int64)
    for k in range(K):
        ok[k] = _one(A[k], b[k], x[k], maxiter_factor * n, G, c, w, idx, free, L, r, y, z, rhs, warm, nwarm[0],
                     nwarm)
        if not ok[k]:
            nwarm[0] = 0
    return x, ok
