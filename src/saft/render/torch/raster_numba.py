"""The depth test of raster.visibility as one numba loop, for CPU tensors.

Why by hand: the torch formulation expands every triangle into its pixel rows and every row into its
pixels as tables (repeat_interleave, index_select) and settles the depth test with one scatter_reduce: on
R1's 700 × 800 frames that is tens of megabytes of temporaries per render, 7 % of a reconstruction's CPU
time. A scanline loop over each triangle's rows and pixels writes the z-buffer directly. The per-triangle
edge functions, the bounding rows and the culling stay in torch (raster.visibility computes them once for
both paths), so both paths cover the same pixels: the same inclusive edge test with the same margin; the
arithmetic is in float64 here, so a pixel centre within rounding of an edge may fall the other way.
Jitted on first use (``load()``), from numba's on-disk cache when there is one.
"""

from __future__ import annotations

import math

from saft.numba_jit import jit_in_place


def load():
    """Jit the kernels; idempotent."""
    jit_in_place(globals(), ("depth_test", "collect"))


def depth_test(tab, row_lo, row_hi, T, H, W, eps, zbuf, rows_used):
    """Fills zbuf (B·H·W,) int64 (initially all int64 max) with min(quantised z/w << 32 | triangle) over the
    triangles covering each pixel centre, and rows_used (B, 2) (initially (H, −1)) with each frame's first and
    last row that a triangle reaches. tab (12, B·T) float64: per triangle b·T + t the edge functions'
    A (rows 0–2), B (3–5) and C (6–8) (inside ⇔ A x + B y + C ≥ 0 for all three) and z/w = zA x + zB y + zC
    (9–11); row_lo, row_hi (B·T,) int64: its first and last pixel row (row_hi < row_lo: skipped)."""
    inf = math.inf
    for it in range(tab.shape[1]):
        if row_hi[it] < row_lo[it]:
            continue
        b = it // T
        t = it - b * T
        za, zb, zc = tab[9, it], tab[10, it], tab[11, it]
        rows_used[b, 0] = min(rows_used[b, 0], row_lo[it])
        rows_used[b, 1] = max(rows_used[b, 1], row_hi[it])
        for row in range(row_lo[it], row_hi[it] + 1):
            left = -inf
            right = inf
            flat_bad = False
            for k in range(3):
                a = tab[k, it]
                bk = tab[3 + k, it]
                num = -(bk * row + tab[6 + k, it])  # inside ⇔ a x ≥ num
                if a > 0:
                    left = max(left, num / a)
                elif a < 0:
                    right = min(right, num / a)
                elif num > eps * abs(bk):
                    flat_bad = True
            if flat_bad:
                continue
            xl = 0 if left == -inf else max(math.ceil(left - eps), 0)
            xr = W - 1 if right == inf else min(math.floor(right + eps), W - 1)
            z_row = zb * row + zc
            base = (b * H + row) * W
            for x in range(xl, xr + 1):
                z = z_row + za * x
                if z < -1.0 or z > 1.0:
                    continue
                key = (int((z + 1.0) * 536870912.0) << 32) | t  # 2**29: 31 bits of depth
                if key < zbuf[base + x]:
                    zbuf[base + x] = key


def collect(zbuf, rows_used, H, W, pix, tid):
    """The covered pixels of zbuf in ascending order into pix, their triangles into tid (both long enough for
    every pixel of the rows used); resets those entries of zbuf to int64 max (so the buffer can serve the next
    call without a refill). Returns how many were written."""
    empty = 0x7FFFFFFFFFFFFFFF  # int64 max
    n = 0
    for b in range(rows_used.shape[0]):
        for i in range((b * H + rows_used[b, 0]) * W, (b * H + rows_used[b, 1] + 1) * W):
            key = zbuf[i]
            if key != empty:
                pix[n] = i
                tid[n] = key & 0xFFFFFFFF
                n += 1
                zbuf[i] = empty
    return n
