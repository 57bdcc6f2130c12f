"""Hand-written numba kernels for the two per-substep element functions of the rollout (CPU, float64,
"projected" Hessian mode): the same closed forms as ``saft.physics.energy.ElementEval``, one loop over
springs and one over hinges, each element's gradient / Hessian entries added straight into the output.

Why hand-written: on a cloth of a few thousand elements every torch op costs more in dispatch and
allocation (a few microseconds each, some fifty ops per kernel) than in arithmetic, and the temporaries
of the elements-last formulation go through memory several times; ``torch.compile`` removes some of that
but needs a C++ toolchain and tens of seconds of compilation per mesh size. Here one pass over the
elements does it all: on the R1 template (1984 springs, 5764 hinges) the forward kernel is about 8x and the
adjoint about 3x faster than the eager torch path (0.55 vs 4.7 ms and 0.63 vs 1.8 ms, warm cache).

Compiled with ``nopython``, ``cache=True`` (the machine code is kept in ``__pycache__``; the first use
on a fresh checkout compiles for a few seconds) and without ``fastmath``, so results are deterministic
and equal the torch reference to rounding (summation order differs). Single-threaded.

The functions below are jitted on the first call of ``load()`` (the first rollout that uses them); until
then the module holds the plain Python functions. (numba itself is imported with saft.physics anyway,
by the solver's ``pcg_numba``.)

The system matrix is assembled as the torch path does: into the upper-triangle storage of
``ClothTopology`` (positions ``spring_up_idx`` / ``hinge_up_idx``; 21 unique entries per spring, 45 per
Gauss-Newton hinge), then expanded to the full symmetric CSR data with ``up_of``, so A is exactly
symmetric.
"""

from __future__ import annotations


import numpy as np

from saft.numba_jit import jit_in_place
from saft.physics.topology import ARCCOS_GUARD

_C = ARCCOS_GUARD
_C3 = ARCCOS_GUARD**3  # the same Python constants as energy.py uses
_C4 = ARCCOS_GUARD**4
_EPS_LEN = 1e-12

_HELPERS = ("_spring_dir", "_hinge_geom", "_hess_q", "_hinge_scalars")  # inlined into the kernels (numba IR level)
_KERNELS = ("step_forward", "step_adjoint")


def load():
    """Jit the kernels (from the on-disk cache when there is one): replaces this module's plain Python
    functions by numba dispatchers, helpers first. Idempotent; raises ImportError without numba."""
    jit_in_place(globals(), _KERNELS, _HELPERS)


def _spring_dir(x, i, j, u):
    """Fills u (3,) with the unit direction of spring (i, j); returns its length (clamped as energy.py)."""
    e0 = x[j, 0] - x[i, 0]
    e1 = x[j, 1] - x[i, 1]
    e2 = x[j, 2] - x[i, 2]
    ls = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    if ls < _EPS_LEN:
        ls = _EPS_LEN
    u[0] = e0 / ls
    u[1] = e1 / ls
    u[2] = e2 / ls
    return ls


def _hinge_geom(x, n1, v, n2, e1, e2, u1, u2):
    """Fills e1, e2, u1, u2 (3,) for hinge (n1, v, n2); returns (l1, l2, q)."""
    for d in range(3):
        e1[d] = x[v, d] - x[n1, d]
        e2[d] = x[n2, d] - x[v, d]
    l1 = np.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    l2 = np.sqrt(e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2])
    if l1 < _EPS_LEN:
        l1 = _EPS_LEN
    if l2 < _EPS_LEN:
        l2 = _EPS_LEN
    for d in range(3):
        u1[d] = e1[d] / l1
        u2[d] = e2[d] / l2
    q = u1[0] * u2[0] + u1[1] * u2[1] + u1[2] * u2[2]
    return l1, l2, q


def _hess_q(u1, u2, q, c11, c12, c22, a1, a2, r1, r2):
    """(grad^2 q) applied to the edge-space vector (a1, a2), into r1, r2 (energy._hess_q; c11, c12, c22 =
    1 / (l1 l1), 1 / (l1 l2), 1 / (l2 l2): multiplications instead of divisions, equal to rounding)."""
    u1a1 = u1[0] * a1[0] + u1[1] * a1[1] + u1[2] * a1[2]
    u2a1 = u2[0] * a1[0] + u2[1] * a1[1] + u2[2] * a1[2]
    u1a2 = u1[0] * a2[0] + u1[1] * a2[1] + u1[2] * a2[2]
    u2a2 = u2[0] * a2[0] + u2[1] * a2[1] + u2[2] * a2[2]
    for d in range(3):
        r1[d] = (-u2a1 * u1[d] - u1a1 * u2[d] - q * a1[d] + 3.0 * q * u1a1 * u1[d]) * c11 + (
            a2[d] - u1a2 * u1[d] - u2a2 * u2[d] + q * u2a2 * u1[d]
        ) * c12
        r2[d] = (-u1a2 * u2[d] - u2a2 * u1[d] - q * a2[d] + 3.0 * q * u2a2 * u2[d]) * c22 + (
            a1[d] - u1a1 * u1[d] - u2a1 * u2[d] + q * u1a1 * u2[d]
        ) * c12


def _hinge_scalars(q, rest, bw, B, S):
    """(kh, dtheta, dth, tau, s2, sqrt(s2)) of one hinge, as ElementEval."""
    cq = _C * q
    if cq < -_C:
        cq = -_C
    elif cq > _C:
        cq = _C
    s2 = 1.0 - cq * cq
    theta = np.arccos(cq)
    rs2 = np.sqrt(s2)
    dth = -_C / rs2
    kh = B * bw + S * (1.0 - bw)
    return kh, theta - rest, dth, dth * dth, s2, rs2


def step_forward(x, edges, rest_len, hinges, rest_angle, bend_w, spring_up, hinge_up, diag_up, up_of,
                 mass_diag, Y, B, S, hh, nnz_up, A):
    """dE/dx (V, 3); writes the data of A = M + hh K (nnz,) into ``A``, K the projected Hessian."""
    V = x.shape[0]
    grad = np.zeros((V, 3))
    Kup = np.zeros(nnz_up)
    u = np.empty(3)
    Ks = np.empty((3, 3))
    # ---- springs: E = 1/2 Y (l - L0)^2
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        L0 = rest_len[k]
        ls = _spring_dir(x, i, j, u)
        s = 1.0 - L0 / ls
        sp = s if s > 0.0 else 0.0
        c = Y * (ls - L0)
        for d in range(3):
            gd = c * u[d]
            grad[i, d] -= gd
            grad[j, d] += gd
        for a in range(3):
            for b in range(3):
                Ks[a, b] = Y * ((1.0 - sp) * (u[a] * u[b]) + (sp if a == b else 0.0))
        p = 0
        for a in range(6):
            for b in range(a, 6):
                val = Ks[a % 3, b % 3]
                if a // 3 != b // 3:
                    val = -val
                Kup[spring_up[k, p]] += val
                p += 1
    # ---- hinges: E = 1/2 k (theta - theta0)^2, Gauss-Newton Hessian k theta'^2 grad q grad q^T
    ev1 = np.empty(3)
    ev2 = np.empty(3)
    u1 = np.empty(3)
    u2 = np.empty(3)
    G = np.empty(9)
    for k in range(hinges.shape[0]):
        n1 = hinges[k, 0]
        v = hinges[k, 1]
        n2 = hinges[k, 2]
        l1, l2, q = _hinge_geom(x, n1, v, n2, ev1, ev2, u1, u2)
        kh, dtheta, dth, tau, s2, rs2 = _hinge_scalars(q, rest_angle[k], bend_w[k], B, S)
        phi_q = kh * dtheta * dth
        phi_qq = kh * tau
        for d in range(3):
            g1 = (u2[d] - q * u1[d]) / l1
            g2 = (u1[d] - q * u2[d]) / l2
            G[d] = -g1
            G[3 + d] = g1 - g2
            G[6 + d] = g2
            P1 = phi_q * g1
            P2 = phi_q * g2
            grad[n1, d] -= P1
            grad[v, d] += P1 - P2
            grad[n2, d] += P2
        p = 0
        for a in range(9):
            ga = phi_qq * G[a]
            for b in range(a, 9):
                Kup[hinge_up[k, p]] += ga * G[b]
                p += 1
    # ---- A = M + hh K, upper storage -> full CSR data
    for m in range(nnz_up):
        Kup[m] = hh * Kup[m]
    for m in range(diag_up.shape[0]):
        Kup[diag_up[m]] += mass_diag[m]
    for m in range(up_of.shape[0]):
        A[m] = Kup[up_of[m]]
    return grad


def step_adjoint(x, lam, w, edges, rest_len, hinges, rest_angle, bend_w, Y, B, S, h):
    """(-h (d2E/dx2) lam - h^2 d/dx (lam^T K(x) w) as (V, 3) (true Hessian in the first term, projected K
    in the second), gY, gB, gS) as ElementEval.adjoint_increment + kernels._step_adjoint."""
    V = x.shape[0]
    hh = h * h
    out = np.zeros((V, 3))
    u = np.empty(3)
    ls_ = np.empty(3)
    ws_ = np.empty(3)
    sY_lg = 0.0
    sY_lKw = 0.0
    # ---- springs
    for k in range(edges.shape[0]):
        i = edges[k, 0]
        j = edges[k, 1]
        L0 = rest_len[k]
        ls = _spring_dir(x, i, j, u)
        s = 1.0 - L0 / ls
        if s > 0.0:
            sp = s
            dsp = L0 / (ls * ls)
        else:
            sp = 0.0
            dsp = 0.0
        for d in range(3):
            ls_[d] = lam[j, d] - lam[i, d]
            ws_[d] = w[j, d] - w[i, d]
        ul = u[0] * ls_[0] + u[1] * ls_[1] + u[2] * ls_[2]
        uw = u[0] * ws_[0] + u[1] * ws_[1] + u[2] * ws_[2]
        lw = ls_[0] * ws_[0] + ls_[1] * ws_[1] + ls_[2] * ws_[2]
        sY_lKw += Y * (sp * lw + (1.0 - sp) * ul * uw)
        sY_lg += Y * (ls - L0) * ul
        for d in range(3):
            P_l = (ls_[d] - ul * u[d]) / ls
            P_w = (ws_[d] - uw * u[d]) / ls
            Ts = Y * ((1.0 - sp) * (uw * P_l + ul * P_w) + (lw - ul * uw) * dsp * u[d])
            Kv = Y * ((1.0 - s) * ul * u[d] + s * ls_[d])
            part = -h * Kv - hh * Ts
            out[i, d] -= part
            out[j, d] += part
    gY = -h * sY_lg - hh * sY_lKw
    # ---- hinges
    ev1 = np.empty(3)
    ev2 = np.empty(3)
    u1 = np.empty(3)
    u2 = np.empty(3)
    g1 = np.empty(3)
    g2 = np.empty(3)
    lam1 = np.empty(3)
    lam2 = np.empty(3)
    w1 = np.empty(3)
    w2 = np.empty(3)
    hl1 = np.empty(3)
    hl2 = np.empty(3)
    hw1 = np.empty(3)
    hw2 = np.empty(3)
    gB = 0.0
    gS = 0.0
    for k in range(hinges.shape[0]):
        n1 = hinges[k, 0]
        v = hinges[k, 1]
        n2 = hinges[k, 2]
        l1, l2, q = _hinge_geom(x, n1, v, n2, ev1, ev2, u1, u2)
        bw = bend_w[k]
        kh, dtheta, dth, tau, s2, rs2 = _hinge_scalars(q, rest_angle[k], bw, B, S)
        phi_q = kh * dtheta * dth
        phi_qq = kh * tau
        d2th = -_C3 * q / (s2 * rs2)
        phi_qq_exact = kh * (tau + dtheta * d2th)
        for d in range(3):
            g1[d] = (u2[d] - q * u1[d]) / l1
            g2[d] = (u1[d] - q * u2[d]) / l2
            lam1[d] = lam[v, d] - lam[n1, d]
            lam2[d] = lam[n2, d] - lam[v, d]
            w1[d] = w[v, d] - w[n1, d]
            w2[d] = w[n2, d] - w[v, d]
        gl = (g1[0] * lam1[0] + g1[1] * lam1[1] + g1[2] * lam1[2]) + (
            g2[0] * lam2[0] + g2[1] * lam2[1] + g2[2] * lam2[2])
        gw = (g1[0] * w1[0] + g1[1] * w1[1] + g1[2] * w1[2]) + (g2[0] * w2[0] + g2[1] * w2[1] + g2[2] * w2[2])
        c11 = 1.0 / (l1 * l1)
        c12 = 1.0 / (l1 * l2)
        c22 = 1.0 / (l2 * l2)
        _hess_q(u1, u2, q, c11, c12, c22, lam1, lam2, hl1, hl2)
        _hess_q(u1, u2, q, c11, c12, c22, w1, w2, hw1, hw2)
        dtau = 2.0 * _C4 * q / (s2 * s2)
        a = kh * dtau * gl * gw
        b = kh * tau
        ax = phi_qq_exact * gl
        for d in range(3):
            T1 = a * g1[d] + b * (gw * hl1[d] + gl * hw1[d])
            T2 = a * g2[d] + b * (gw * hl2[d] + gl * hw2[d])
            H1 = ax * g1[d] + phi_q * hl1[d]
            H2 = ax * g2[d] + phi_q * hl2[d]
            P1 = -h * H1 - hh * T1
            P2 = -h * H2 - hh * T2
            out[n1, d] -= P1
            out[v, d] += P1 - P2
            out[n2, d] += P2
        hc = -h * (phi_q * gl) - hh * (phi_qq * gl * gw)
        gB += hc * bw
        gS += hc * (1.0 - bw)
    return out, gY, gB, gS


class NumbaGeo:
    """The topology arrays the numba kernels read, as contiguous numpy arrays (made once per topology)."""

    def __init__(self, t):
        def np_(a):
            return np.ascontiguousarray(a.detach().cpu().numpy())

        E, H = t.num_springs, t.num_hinges
        self.edges = np_(t.edges)
        self.rest_len = np_(t.rest_len).astype(np.float64)
        self.hinges = np_(t.hinges)
        self.rest_angle = np_(t.rest_angle).astype(np.float64)
        self.bend_w = np_(t.bend_w).astype(np.float64)
        # per element, its unique Hessian entries' positions in the upper-triangle storage (pair-major in
        # the topology, element-major here)
        # the index maps are the bulk of the forward kernel's memory traffic: int32 when they fit
        it = np.int32 if t.nnz < 2**31 else np.int64
        self.spring_up = np.ascontiguousarray(np_(t.spring_up_idx).reshape(21, E).T.astype(it))
        self.hinge_up = np.ascontiguousarray(np_(t.hinge_up_idx).reshape(45, H).T.astype(it))
        self.diag_up = np_(t.diag_up_idx).astype(it)
        self.up_of = np_(t.up_of).astype(it)
        self.nnz_up = int(t.nnz_up)

