"""Numba kernels of the CPU solver (``solver.ReusedLUSolver``): the whole preconditioned CG loop in one call.

The preconditioner is a symmetric factorisation of a permuted matrix, P A P^T ~ (I + U)^T D (I + U), with
U strictly upper triangular, stored once by columns (CSC: uint32 indices, float32 values) and 1 / D in
float64 (see ``factors_from_superlu``). Applying it to r:

    y[k] = r[inv[k]]                                  (y = P r; inv[perm[k]] = k)
    s[j] = y[j] - sum_{i<j} U[i, j] s[i]             (forward, (I + U)^T s = y)
    t[j] = s[j] / D[j]
    w[j] = t[j] - sum_{k>j} U[j, k] w[k]             (backward, (I + U) w = t)
    z[i] = w[perm[i]]                                 (z = P^T w)

The arithmetic is float64 (the float32 values are widened), in a fixed order: the same inputs give the
same bits on every run. No fastmath, single-threaded. Index arrays are unsigned so that numba skips its
negative-index wraparound test (2.4x faster CSR products here).
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
def _spmv(aptr, aidx, aval, mode, v, out):
    """out = A v. ``mode`` 0: A in CSR (aptr, aidx, aval), for any pattern. 2: A symmetric, stored as its
    upper 3x3 blocks (``sym_blocks``, for patterns with ``is_blocked``): aptr over vertex rows, aidx the
    block columns (vertices, the diagonal block first in each row), aval nine row-major values per block;
    each off-diagonal block is read once for both of its products (half the memory traffic of a blocked
    CSR product, which was measured at 30 us against 22 on R1 and is no longer kept)."""
    n = v.shape[0]
    if mode == 0:
        for i in range(n):
            out[i] = _row_dot(aptr, aidx, aval, i, v)
        return
    if mode != 2:
        raise ValueError("_spmv: mode must be 0 (CSR) or 2 (symmetric upper 3x3 blocks)")
    for i in range(n):
        out[i] = 0.0
    for vv in range(aptr.shape[0] - 1):
        i = 3 * vv
        x0 = v[i]
        x1 = v[i + 1]
        x2 = v[i + 2]
        a = aptr[vv]
        q = 9 * a
        y0 = aval[q] * x0 + aval[q + 1] * x1 + aval[q + 2] * x2
        y1 = aval[q + 3] * x0 + aval[q + 4] * x1 + aval[q + 5] * x2
        y2 = aval[q + 6] * x0 + aval[q + 7] * x1 + aval[q + 8] * x2
        for bb in range(a + 1, aptr[vv + 1]):
            c = 3 * aidx[bb]
            q = 9 * bb
            u0 = v[c]
            u1 = v[c + 1]
            u2 = v[c + 2]
            y0 += aval[q] * u0 + aval[q + 1] * u1 + aval[q + 2] * u2
            y1 += aval[q + 3] * u0 + aval[q + 4] * u1 + aval[q + 5] * u2
            y2 += aval[q + 6] * u0 + aval[q + 7] * u1 + aval[q + 8] * u2
            out[c] += aval[q] * x0 + aval[q + 3] * x1 + aval[q + 6] * x2
            out[c + 1] += aval[q + 1] * x0 + aval[q + 4] * x1 + aval[q + 7] * x2
            out[c + 2] += aval[q + 2] * x0 + aval[q + 5] * x1 + aval[q + 8] * x2
        out[i] += y0
        out[i + 1] += y1
        out[i + 2] += y2


@njit(cache=_CACHE, nogil=True)
def gather(data, src):
    out = np.empty(src.shape[0])
    for k in range(src.shape[0]):
        out[k] = data[src[k]]
    return out


def sym_blocks(indptr, indices):
    """For a pattern with ``is_blocked``: (bptr, bcol, src) of its upper 3x3 blocks for ``_spmv`` mode 2,
    bptr over vertex rows, bcol the block columns (the diagonal block first in each row; None if a
    diagonal block is missing), src the positions in the CSR data of each block's nine values."""
    indptr = np.asarray(indptr, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    nv = (len(indptr) - 1) // 3
    r0 = indptr[0:-1:3]  # start of each vertex's first row
    cnt = indptr[1::3] - r0
    v = np.repeat(np.arange(nv), cnt // 3)
    nb = cnt // 3
    e = np.repeat(r0, nb) + 3 * (np.arange(nb.sum()) - np.repeat(np.cumsum(nb) - nb, nb))  # each block's entry
    u = indices[e] // 3
    up = u >= v
    v, e, u = v[up], e[up], u[up]
    bptr = np.zeros(nv + 1, np.int64)
    np.cumsum(np.bincount(v, minlength=nv), out=bptr[1:])
    if not np.array_equal(u[bptr[:-1]], np.arange(nv)):
        return None
    k = e - r0[v]  # offset of the block in its rows
    rows = indptr[3 * v[:, None] + np.arange(3)[None, :]]  # (blocks, 3): start of each of the three rows
    src = (rows[:, :, None] + k[:, None, None] + np.arange(3)[None, None, :]).reshape(-1)
    return bptr.astype(np.uint32), u.astype(np.uint32), src.astype(np.uint32)


def is_blocked(indptr, indices) -> bool:
    """Whether a CSR pattern is made of 3x3 blocks in the layout ``_spmv`` uses: n a multiple of 3, the
    three rows 3v, 3v+1, 3v+2 with the same columns, those in runs 3u, 3u+1, 3u+2 (saft's layout)."""
    indptr = np.asarray(indptr, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    n = len(indptr) - 1
    if n % 3:
        return False
    cnt = np.diff(indptr)
    c0 = cnt[0::3]
    if np.any(c0 % 3) or not (np.array_equal(c0, cnt[1::3]) and np.array_equal(c0, cnt[2::3])):
        return False
    row = np.repeat(np.arange(n), cnt)
    pos = np.arange(len(indices)) - indptr[row]  # position within the row
    first = indptr[row - row % 3] + pos  # the same position in the vertex's first row
    if not np.array_equal(indices, indices[first]):
        return False
    c = indices[indptr[row] + pos - pos % 3]  # the first column of each entry's triple
    return bool(np.array_equal(indices, c + pos % 3) and np.all(c % 3 == 0))


@njit(cache=_CACHE, nogil=True)
def _precond(perm, inv, uptr, uidx, uval, dinv, r, w, z):
    """z = M^{-1} r with M = P^T (I + U)^T D (I + U) P; w is scratch (length n).

    U (strictly upper, unit-scaled) is stored once, by columns (CSC): the forward solve with (I + U)^T
    reads column j as row j of U^T (a dot product, two partial sums: fixed order, deterministic), the
    backward solve with (I + U) scatters column j into the entries above it."""
    n = r.shape[0]
    for j in range(n):
        s0 = r[inv[j]]
        s1 = 0.0
        a = uptr[j]
        e = uptr[j + 1]
        while a + 1 < e:
            s0 -= uval[a] * w[uidx[a]]
            s1 -= uval[a + 1] * w[uidx[a + 1]]
            a += 2
        if a < e:
            s0 -= uval[a] * w[uidx[a]]
        w[j] = s0 + s1
    for j in range(n):
        w[j] *= dinv[j]
    for jj in range(n):
        j = n - 1 - jj
        wj = w[j]
        for a in range(uptr[j], uptr[j + 1]):
            w[uidx[a]] -= uval[a] * wj
    for i in range(n):
        z[i] = w[perm[i]]


@njit(cache=_CACHE, nogil=True)
def precond_apply(perm, inv, uptr, uidx, uval, dinv, r):
    n = r.shape[0]
    w = np.empty(n)
    z = np.empty(n)
    _precond(perm, inv, uptr, uidx, uval, dinv, r, w, z)
    return z


@njit(cache=_CACHE, nogil=True)
def pcg(aptr, aidx, aval, mode, b, x, atol, max_iter,
        perm, inv, uptr, uidx, uval, dinv):
    """Preconditioned CG for A x = b (A in CSR, float64), from the start ``x`` (updated in place).

    ``mode``: the storage of A, see ``_spmv``. Same algorithm as the reference ``ReusedLUSolver._pcg_reference``:
    flexible (Polak-Ribiere) beta, stop when ||r|| <= atol. Returns (status, iterations): status 0
    converged, 1 breakdown (r.z or p.Ap not positive: A or the preconditioner indefinite), 2 max_iter.
    """
    n = b.shape[0]
    r = np.empty(n)
    z = np.empty(n)
    p = np.empty(n)
    ap = np.empty(n)
    w = np.empty(n)
    _spmv(aptr, aidx, aval, mode, x, ap)
    rr = 0.0
    for i in range(n):
        ri = b[i] - ap[i]
        r[i] = ri
        rr += ri * ri
    if np.sqrt(rr) <= atol:
        return 0, 0
    _precond(perm, inv, uptr, uidx, uval, dinv, r, w, z)
    rz = 0.0
    for i in range(n):
        p[i] = z[i]
        rz += r[i] * z[i]
    for it in range(max_iter):
        if not rz > 0.0:
            return 1, it
        _spmv(aptr, aidx, aval, mode, p, ap)
        pap = 0.0
        for i in range(n):
            pap += p[i] * ap[i]
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
        _precond(perm, inv, uptr, uidx, uval, dinv, r, w, z)
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


def factors_from_superlu(lu, f32: bool = True):
    """The symmetric preconditioner made from a scipy SuperLU factorisation in symmetric mode (Pr A Pc = L U
    with Pr = Pc^T, diagonal pivots): U = D (I + U1) gives M = P^T (I + U1)^T D (I + U1) P. For a complete
    factorisation of a symmetric A, L = (I + U1)^T up to rounding, so M = A. For SuperLU's incomplete one
    (which keeps about twice as many entries in L as in U) M uses U alone: it is symmetric, costs a third
    of L and U's triangular solves, and CG needs as many iterations (4757 against 4715 over R1's 392
    solves of a fwd+bwd rollout).

    Returns the argument tuple (perm, inv, uptr, uidx, uval, dinv) of ``pcg`` / ``precond_apply``: index
    arrays uint32, U1's values float32 (``f32``) or float64, 1 / D float64."""
    perm_r = np.asarray(lu.perm_r)
    if not np.array_equal(perm_r, np.asarray(lu.perm_c)):
        raise ValueError("factors_from_superlu needs a symmetric permutation (perm_r == perm_c)")
    n = perm_r.shape[0]
    inv = np.empty(n, np.uint32)
    inv[perm_r] = np.arange(n, dtype=np.uint32)
    U = sp.csc_matrix(lu.U)
    cols = np.repeat(np.arange(n, dtype=np.int32), np.diff(U.indptr))
    rows = U.indices
    on_diag = rows == cols
    d = np.zeros(n)
    d[cols[on_diag]] = U.data[on_diag]
    if not np.all(d != 0.0):
        raise ValueError("zero pivot in the factorisation")
    off = ~on_diag
    ptr = np.zeros(n + 1, np.uint32)
    np.cumsum(np.bincount(cols[off], minlength=n), out=ptr[1:])
    val = (U.data[off].astype(np.float64) / d[rows[off]]).astype(np.float32 if f32 else np.float64)
    return perm_r.astype(np.uint32), inv, ptr, rows[off].astype(np.uint32), val, 1.0 / d
