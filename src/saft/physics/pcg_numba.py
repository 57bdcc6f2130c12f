"""Numba kernels of the CPU solver (``solver.ReusedLUSolver``): the whole preconditioned CG loop in one call.

The preconditioner is a pair of sparse triangular factors of a permuted matrix, P A P^T ~ L U, stored as
CSR arrays (int32 indices, float32 values) with the diagonals kept apart as float64 inverses:

    y[k] = r[inv[k]]                      (y = P r; inv[perm[i]] = i)
    s[k] = (y[k] - sum_{j<k} L[k, j] s[j]) * ldinv[k]
    w[k] = (s[k] - sum_{j>k} U[k, j] w[j]) * udinv[k]
    z[i] = w[perm[i]]                     (z = P^T w)

``factors_from_superlu`` makes them from a scipy ``SuperLU`` object (complete or incomplete LU, which
satisfies Pr A Pc = L U; the solver only factorises with Pr = Pc^T, symmetric mode). The arithmetic is
float64 (the float32 values are widened), in a fixed order: the same inputs give the same bits on every
run. No fastmath, single-threaded.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit

_CACHE = True


@njit(cache=_CACHE, nogil=True, inline="always")
def _row_dot(ptr, idx, val, k, v):
    """sum_j val[j] * v[idx[j]] over row k, in index order. The index arrays are unsigned (uint32):
    numba then skips the negative-index wraparound test, which otherwise costs more than half the time."""
    s = 0.0
    for a in range(ptr[k], ptr[k + 1]):
        s += val[a] * v[idx[a]]
    return s


@njit(cache=_CACHE, nogil=True)
def _precond(perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv, r, w, z):
    """z = M^{-1} r with M = P^T L U P; w is scratch (length n). The strict triangles are stored by
    columns (CSC) and the solves are column-oriented (each solved entry is scattered into the rest of
    the right-hand side): no long chains of dependent additions, 1.7x faster than row-oriented here."""
    n = r.shape[0]
    for k in range(n):
        w[k] = r[inv[k]]
    for j in range(n):
        s = w[j] * ldinv[j]
        w[j] = s
        for a in range(lptr[j], lptr[j + 1]):
            w[lidx[a]] -= lval[a] * s
    for jj in range(n):
        j = n - 1 - jj
        s = w[j] * udinv[j]
        w[j] = s
        for a in range(uptr[j], uptr[j + 1]):
            w[uidx[a]] -= uval[a] * s
    for i in range(n):
        z[i] = w[perm[i]]


@njit(cache=_CACHE, nogil=True)
def precond_apply(perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv, r):
    n = r.shape[0]
    w = np.empty(n)
    z = np.empty(n)
    _precond(perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv, r, w, z)
    return z


@njit(cache=_CACHE, nogil=True)
def pcg(aptr, aidx, aval, b, x, atol, max_iter,
        perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv):
    """Preconditioned CG for A x = b (A in CSR, float64), from the start ``x`` (updated in place).

    Same algorithm as the reference ``ReusedLUSolver._pcg_reference``: flexible (Polak-Ribiere) beta, stop
    when ||r|| <= atol. Returns (status, iterations): status 0 converged, 1 breakdown (r.z or p.Ap not
    positive: A or the preconditioner indefinite), 2 max_iter reached.
    """
    n = b.shape[0]
    r = np.empty(n)
    z = np.empty(n)
    p = np.empty(n)
    ap = np.empty(n)
    w = np.empty(n)
    rr = 0.0
    for i in range(n):
        ri = b[i] - _row_dot(aptr, aidx, aval, i, x)
        r[i] = ri
        rr += ri * ri
    if np.sqrt(rr) <= atol:
        return 0, 0
    _precond(perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv, r, w, z)
    rz = 0.0
    for i in range(n):
        p[i] = z[i]
        rz += r[i] * z[i]
    for it in range(max_iter):
        if not rz > 0.0:
            return 1, it
        pap = 0.0
        for i in range(n):
            a = _row_dot(aptr, aidx, aval, i, p)
            ap[i] = a
            pap += p[i] * a
        if not pap > 0.0:
            return 1, it
        alpha = rz / pap
        rr = 0.0
        for i in range(n):
            x[i] += alpha * p[i]
            ri = r[i] - alpha * ap[i]
            r[i] = ri
            rr += ri * ri
        if np.sqrt(rr) <= atol:
            return 0, it + 1
        _precond(perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv, r, w, z)
        rz_new = 0.0
        zap = 0.0
        for i in range(n):
            rz_new += r[i] * z[i]
            zap += z[i] * ap[i]
        # flexible beta = z_new . (r_new - r_old) / rz, with r_new - r_old = -alpha Ap
        beta = -alpha * zap / rz
        for i in range(n):
            p[i] = z[i] + beta * p[i]
        rz = rz_new
    return 2, max_iter


def _strict_csc(T, n, vdt):
    """(indptr, indices, values) of T's off-diagonal entries by columns, and 1 / T's diagonal."""
    T = sp.csc_matrix(T)
    cols = np.repeat(np.arange(n, dtype=np.int32), np.diff(T.indptr))
    rows = T.indices
    on_diag = rows == cols
    d = np.zeros(n)
    d[cols[on_diag]] = T.data[on_diag]
    off = ~on_diag
    ptr = np.zeros(n + 1, np.uint32)
    np.cumsum(np.bincount(cols[off], minlength=n), out=ptr[1:])
    return ptr, rows[off].astype(np.uint32), T.data[off].astype(vdt), 1.0 / d


def factors_from_superlu(lu, f32: bool = True):
    """Triangular factors of a scipy SuperLU object (Pr A Pc = L U, with Pr = Pc^T) as the argument tuple
    (perm, inv, lptr, lidx, lval, ldinv, uptr, uidx, uval, udinv) of ``pcg`` / ``precond_apply``.
    Index arrays are uint32, values float32 (``f32``) or float64, inverse diagonals float64."""
    perm_r = np.asarray(lu.perm_r)
    if not np.array_equal(perm_r, np.asarray(lu.perm_c)):
        raise ValueError("factors_from_superlu needs a symmetric permutation (perm_r == perm_c)")
    n = perm_r.shape[0]
    vdt = np.float32 if f32 else np.float64
    inv = np.empty(n, np.uint32)
    inv[perm_r] = np.arange(n, dtype=np.uint32)
    return (perm_r.astype(np.uint32), inv) + _strict_csc(lu.L, n, vdt) + _strict_csc(lu.U, n, vdt)
