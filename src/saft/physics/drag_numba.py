"""The air drag's force and its vector-Jacobian product (saft.physics.drag) as numba loops, for CPU float64.

Why by hand: the torch formulation is ~40 small ops per call on (T, 3) arrays, called twice per substep
(force in the forward pass, its adjoint in the backward): on a 25 × 25 swinging cloth 4 % of a whole
reconstruction, all of it on the physics' critical path. These loops do the same arithmetic in the same order,
element by element (the cross products as ATen writes them, three-term sums left to right, the corners'
shares added triangle by triangle as index_add_ does), so that they give the torch path's bits; the tests
compare them bit for bit. The one long sum, the coefficient's gradient over all triangles, stays in torch
(its order is torch's reduction's). Compiled with ``cache=True``, without ``fastmath``, single-threaded.
"""

from __future__ import annotations

import numpy as np

from saft.numba_jit import jit_in_place


def _fma_intrinsic():
    """fma(a, b, c) = a b + c rounded once (LLVM's llvm.fma): ATen's cross product computes each component as
    fma(a1, b2, -(a2 b1)) (measured on this project's CPU build), and these loops must give its bits."""
    from numba.core import types
    from numba.extending import intrinsic

    @intrinsic
    def fma(typingctx, a, b, c):
        def codegen(context, builder, signature, args):
            return builder.fma(*args)
        return types.float64(types.float64, types.float64, types.float64), codegen

    return fma


def fma(a, b, c):
    """a b + c (the plain-Python stand-in; load() puts the once-rounded intrinsic here)."""
    return a * b + c


def _cross(a0, a1, a2, b0, b1, b2):
    """a x b as torch.linalg.cross computes it."""
    return fma(a1, b2, -(a2 * b1)), fma(a2, b0, -(a0 * b2)), fma(a0, b1, -(a1 * b0))


def load():
    """Jit the kernels (from numba's on-disk cache when there is one); idempotent."""
    if not globals().get("_jitted"):
        globals()["fma"] = _fma_intrinsic()
    # error_model "numpy": a collapsed triangle divides by zero as torch does (inf / nan, then the rollout's
    # finite checks name the substep) instead of raising ZeroDivisionError
    jit_in_place(globals(), ("force", "vjp"), ("_cross", "_terms"), error_model="numpy")


def _terms(x, v, tri, t, out):
    """Triangle t's e1, e2, N, w into out[0:12] and (un, nn) as the return value (drag._triangle_terms)."""
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    for k in range(3):
        out[k] = x[b, k] - x[a, k]
        out[3 + k] = x[c, k] - x[a, k]
        out[9 + k] = ((v[a, k] + v[b, k]) + v[c, k]) / 3.0
    out[6], out[7], out[8] = _cross(out[0], out[1], out[2], out[3], out[4], out[5])
    un = (out[6] * out[9] + out[7] * out[10]) + out[8] * out[11]
    nn = (out[6] * out[6] + out[7] * out[7]) + out[8] * out[8]
    if nn < 2.2250738585072014e-308:   # clamp_min(finfo(float64).tiny)
        nn = 2.2250738585072014e-308
    return un, nn


def force(x, v, tri, c, out):
    """drag.drag_force into out (V, 3), zeroed here; c the coefficient (float)."""
    out[:, :] = 0.0
    e = np.empty(12)
    mc = -0.5 * c
    for t in range(tri.shape[0]):
        un, nn = _terms(x, v, tri, t, e)
        s = (abs(un) * un) / nn
        for j in range(3):
            vert = tri[t, j]
            for k in range(3):
                out[vert, k] += ((mc * e[6 + k]) * s) / 3.0


def vjp(x, v, tri, c, lam, gx, gv, gc_terms):
    """drag.drag_vjp: gx, gv (V, 3) zeroed and filled here; gc_terms (T,) each triangle's term of d/dc, for
    torch to sum."""
    gx[:, :] = 0.0
    gv[:, :] = 0.0
    e = np.empty(12)
    L = np.empty(3)
    gN = np.empty(3)
    mc = -0.5 * c
    for t in range(tri.shape[0]):
        un, nn = _terms(x, v, tri, t, e)
        i0, i1, i2 = tri[t, 0], tri[t, 1], tri[t, 2]
        for k in range(3):
            L[k] = ((lam[i0, k] + lam[i1, k]) + lam[i2, k]) / 3.0
        p = (L[0] * e[6] + L[1] * e[7]) + L[2] * e[8]
        au = abs(un)
        s = au * un
        gc_terms[t] = -0.5 * ((p * s) / nn)
        fw = (((-c) * p) * au) / nn
        a1 = s / nn
        a2 = ((2.0 * p) * au) / nn
        a3 = ((2.0 * p) * s) / (nn * nn)
        for k in range(3):
            gN[k] = mc * ((a1 * L[k] + a2 * e[9 + k]) - a3 * e[6 + k])
        # ge1 = e2 x gN, ge2 = gN x e1
        g10, g11, g12 = _cross(e[3], e[4], e[5], gN[0], gN[1], gN[2])
        g20, g21, g22 = _cross(gN[0], gN[1], gN[2], e[0], e[1], e[2])
        for j in range(3):
            vert = tri[t, j]
            for k in range(3):
                gv[vert, k] += (fw * e[6 + k]) / 3.0
        gx[i0, 0] += -g10 - g20
        gx[i0, 1] += -g11 - g21
        gx[i0, 2] += -g12 - g22
        gx[i1, 0] += g10
        gx[i1, 1] += g11
        gx[i1, 2] += g12
        gx[i2, 0] += g20
        gx[i2, 1] += g21
        gx[i2, 2] += g22
