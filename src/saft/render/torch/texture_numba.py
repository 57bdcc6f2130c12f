"""texture_fast's lookup and its adjoint as two numba loops, for CPU tensors.

Why by hand: the torch formulation (fused_texture._TexFn) builds every tap's index, weight and value as a
(4 taps, 2 levels, P) temporary: on R1's 700 × 800 frames (P ≈ 190k covered pixels) that is ~20 passes
over tens of megabytes per render, and the lookup was 17 % of a reconstruction's CPU time. One pass per
pixel, with the taps in registers, does the same arithmetic. The adjoint recomputes the taps from the
coordinates instead of saving them. The pyramid (and its adjoint) stays in torch: it is made once per
texture.

The same arithmetic as the torch path, in float64 (the torch path works in the coordinates' and the
texture's dtypes, so the two agree to float32 rounding when those are float32, and to 1e-12 in float64).
Compiled with ``cache=True``, without ``fastmath`` (deterministic); single-threaded. Jitted on first use
(``load()``).
"""

from __future__ import annotations

import math

import numpy as np

from saft.numba_jit import jit_in_place


def load():
    """Jit the kernels (from numba's on-disk cache when there is one); idempotent."""
    jit_in_place(globals(), ("lookup", "lookup_adjoint"), ("_taps",))


def _taps(u, v, gf, gi, level, out_i, out_w):
    """Bilinear taps of (u, v) on one mip level (clamp to edge): fills out_i (4,) with texel indices into the
    flat pyramid and out_w (4,) with their weights (00, 01, 10, 11); returns (fx, fy, d/dx factor, d/dy
    factor): the level's width and height where the point is strictly inside, else 0 (grid_sample's
    coordinate gradient)."""
    w_ = gf[0, level]
    h_ = gf[1, level]
    x = u * w_ - 0.5
    y = v * h_ - 0.5
    sx = w_ if (x > 0.0 and x < w_ - 1.0) else 0.0
    sy = h_ if (y > 0.0 and y < h_ - 1.0) else 0.0
    x = min(max(x, 0.0), w_ - 1.0)
    y = min(max(y, 0.0), h_ - 1.0)
    x0 = min(math.floor(x), gf[2, level])  # the left/top tap at most at w − 2 / h − 2
    y0 = min(math.floor(y), gf[3, level])
    fx = x - x0
    fy = y - y0
    base = int(y0 * w_ + x0)
    for t in range(4):
        out_i[t] = base + gi[t, level]
    out_w[0] = (1.0 - fx) * (1.0 - fy)
    out_w[1] = fx * (1.0 - fy)
    out_w[2] = (1.0 - fx) * fy
    out_w[3] = fx * fy
    return fx, fy, sx, sy


def lookup(flat, C, gf, gi, u, v, lo, frac, n_levels, out):
    """out (C, P) = the trilinear lookup of every (u[p], v[p]) in the flat pyramid (texel k, channel c at
    flat[k·C + c]); lo / frac (P,) the lower mip level and the upper one's weight, or empty: level 0 only."""
    P = u.shape[0]
    two = lo.shape[0] > 0
    idx = np.empty(4, np.int64)
    w = np.empty(4, np.float64)
    for p in range(P):
        for c in range(C):
            out[c, p] = 0.0
        nl = 2 if two else 1
        for k in range(nl):
            level = min(lo[p] + k, n_levels - 1) if two else 0
            lw = 1.0 if not two else (frac[p] if k == 1 else 1.0 - frac[p])
            _taps(u[p], v[p], gf, gi, level, idx, w)
            for c in range(C):
                s = 0.0
                for t in range(4):
                    s += flat[idx[t] * C + c] * w[t]
                out[c, p] += s * lw


def lookup_adjoint(flat, C, gf, gi, u, v, lo, frac, n_levels, g, gflat, gu, gv, need_tex, need_uv):
    """The adjoint of lookup for the output gradient g (C, P): adds into gflat (the flat pyramid's gradient)
    when need_tex, and writes gu, gv (P,) when need_uv."""
    P = u.shape[0]
    two = lo.shape[0] > 0
    idx = np.empty(4, np.int64)
    w = np.empty(4, np.float64)
    gd = np.empty(4, np.float64)
    for p in range(P):
        su = 0.0
        sv = 0.0
        nl = 2 if two else 1
        for k in range(nl):
            level = min(lo[p] + k, n_levels - 1) if two else 0
            lw = 1.0 if not two else (frac[p] if k == 1 else 1.0 - frac[p])
            fx, fy, sx, sy = _taps(u[p], v[p], gf, gi, level, idx, w)
            if need_tex:
                for t in range(4):
                    for c in range(C):
                        gflat[idx[t] * C + c] += w[t] * lw * g[c, p]
            if need_uv:
                for t in range(4):
                    s = 0.0
                    for c in range(C):
                        s += flat[idx[t] * C + c] * g[c, p]
                    gd[t] = s * lw
                su += ((1.0 - fy) * (gd[1] - gd[0]) + fy * (gd[3] - gd[2])) * sx
                sv += ((1.0 - fx) * (gd[2] - gd[0]) + fx * (gd[3] - gd[1])) * sy
        if need_uv:
            gu[p] = su
            gv[p] = sv
