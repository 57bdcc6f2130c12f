"""The fused torch path of render_cloth: everything on the covered pixels only, hand-written backwards.

plane_table / plane_interp give barycentrics, attributes and their screen derivatives as ratios of affine
functions of the pixel position (one per-triangle row of plane coefficients, one gather per pixel, one
index_add in the backward), and texture_fast (fused_texture) is a clamp-mode trilinear lookup,
structure-of-arrays, with the levels in the caller's HWC layout. render_cloth_fused equals the primitive pipeline
(saft.render.reference.render_cloth_primitives with the TorchRasterizer) in value and gradient (tested).
On CPU, small-dimension reductions, advanced indexing and strided (transposing) copies are several times
slower than contiguous elementwise ops and 1-D index_select/index_add: the kernels avoid them.
"""

from __future__ import annotations

import math

import torch

from saft.render.output import RenderOutput, no_normals, vertex_normals
from saft.render.topology import topology
from saft.render.torch.antialias import antialias_core
from saft.render.torch.raster import W_EPS, visibility
from saft.render.torch.fused_texture import texture_fast
from saft.render.torch.rows import ScatterPlanar, const, scatter_rows

# In clip space the (unnormalised) perspective-correct barycentric of
# vertex k at the pixel whose ray has NDC (nx, ny) is c_k = X_i Y_j − X_j Y_i (i, j = k+1, k+2) with
# X = x − nx·w, Y = y − ny·w; the nx·ny terms cancel, so c_k is AFFINE in (nx, ny), and so is Σ_k c_k a_k
# for any vertex attribute a. Every interpolated quantity is then (affine numerator) / (affine s = Σ c_k):
# one row of plane coefficients per triangle, one gather per pixel, one index_add per backward.
PLANE_COLS = ("s", "u", "v", "w", "n0", "n1", "n2", "c0", "c1", "z")
_NP = len(PLANE_COLS)  # numerators per triangle
_NG = 7  # the leading columns that can carry gradient (s, u, v, w, normal)


def plane_table(pos: torch.Tensor, tri: torch.Tensor, uv: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """(B·T, 2 + 3·10) per-triangle rows [rx, ry, α(10), β(10), γ(10)]: numerator j at NDC (nx, ny) is
    α_j + β_j (nx − rx) + γ_j (ny − ry), for the columns PLANE_COLS (s = Σ c_k, the attributes u, v (B|1, V,
    2), w, normals (B, V, 3) times c, c0, c1 and c·z). (rx, ry) is the NDC of the triangle's clip-space
    centroid (a constant of the expansion, kept close to the pixels for precision; no gradient).
    Differentiable (plain autograd: it is per triangle, not per pixel)."""
    B = pos.shape[0]
    T = tri.shape[0]
    tf = topology(tri).tri.reshape(-1)
    p = pos.index_select(1, tf).reshape(B, T, 3, 4)  # index_select: its backward is an index_add
    # unbind, stack and cat, not slices: their backwards are views and one stack, where every slice of a
    # tensor with gradient would zero-fill and copy
    x, y, z, w = p.unbind(-1)  # (B, T, 3)
    with torch.no_grad():
        s4 = p.sum(2)  # (B, T, x|y|z|w)
        ok = s4[..., 3:].abs() > W_EPS
        nok = ~ok
        r = (s4[..., :2] / s4[..., 3:].masked_fill(nok, 1.0)).masked_fill(nok, 0.0)  # (B, T, 2): rx, ry
        rx, ry = r[..., 0:1], r[..., 1:2]
    # rows (X, Y, w) over the three vertices: c = X × Y (α, c_k at (rx, ry)), Y × w (β = dc/dnx) and
    # w × X (γ = dc/dny), one cross product of the rows with the rows rolled by one
    M = torch.stack([x - rx * w, y - ry * w, w], dim=-2)  # (B, T, 3 rows, 3 vertices)
    cm = torch.linalg.cross(M, M.roll(-1, -2), dim=-1)  # (B, T, 3 coef, 3 vertex)
    if uv.dim() == 2:
        uv = uv[None]
    # per triangle vertex the columns PLANE_COLS multiply c by: 1, u, v, w, n, e0, e1 (c0, c1 themselves), z
    uvt = uv.expand(B, -1, -1).index_select(1, tf).reshape(B, T, 3, 2)
    nt = normals.index_select(1, tf).reshape(B, T, 3, 3)
    k = const(((1.0, 1.0, 0.0), (1.0, 0.0, 1.0), (1.0, 0.0, 0.0)), nt).expand(B, T, 3, 3)
    tab = cm @ torch.cat([k[..., :1], uvt.to(nt.dtype), w[..., None], nt, k[..., 1:], z[..., None]], dim=-1)
    return torch.cat([r.reshape(B * T, 2), tab.reshape(B * T, 3 * _NP)], dim=1)


class _PlaneFn(torch.autograd.Function):
    """Per-pixel evaluation of a plane_table, structure-of-arrays (one row per quantity, contiguous over
    pixels): uv (2, P), depth w (P,), normal (3, P) with gradient to the table, and without gradient
    bw (2, P), z/w (P,), uv_da (4, P) = (du/dX, du/dY, dv/dX, dv/dY) in pixels."""

    @staticmethod
    def forward(ctx, table, idx, nx, ny, H, W):
        ctx.set_materialize_grads(False)
        # (32, P): one gather, rows contiguous over pixels (with torch 2.13 on CPU faster than one 1-D
        # gather per row: 1.9 vs 2.2 ms at 200k pixels, measured)
        g = table.T.contiguous().index_select(1, idx)
        dx = nx - g[0]
        dy = ny - g[1]
        a, b, c = g[2:2 + _NP], g[2 + _NP:2 + 2 * _NP], g[2 + 2 * _NP:]
        num = torch.addcmul(a, b, dx)
        num.addcmul_(c, dy)  # (10, P)
        s = num[0]
        inv_s = s.masked_fill(s == 0, 1.0).reciprocal_()
        vals = num[1:9] * inv_s  # u, v, w, n0, n1, n2, bw0, bw1
        uv, depth, nrm, bw = vals[0:2], vals[2], vals[3:6], vals[6:8]
        cw = num[3]
        zw = num[9] / cw.masked_fill(cw == 0, 1.0)
        # screen derivatives of u and v: d(N/s) = (dN − (N/s) ds)/s, NDC → pixels: ×2/W, ×2/H; as
        # (dX|dY, u|v, P) = (b|c rows 1, 2 − (u, v)·(b|c row 0))·(2/W | 2/H) / s, written as (u|v, dX|dY, P)
        bc = g[2 + _NP:].view(2, _NP, -1)
        sxy = inv_s * const((2.0 / W, 2.0 / H), inv_s).view(2, 1)
        uv_da = torch.empty(2, 2, uv.shape[1], dtype=uv.dtype, device=uv.device)
        torch.mul(bc[:, 1:3] - uv[None] * bc[:, 0:1], sxy[:, None], out=uv_da.transpose(0, 1))
        uv_da = uv_da.view(4, -1)
        ctx.mark_non_differentiable(bw, zw, uv_da)
        ctx.save_for_backward(idx, dx, dy, inv_s, vals)
        ctx.m = table.shape[0]
        return uv, depth, nrm, bw, zw, uv_da

    @staticmethod
    def backward(ctx, g_uv, g_depth, g_n, *_):
        idx, dx, dy, inv_s, vals = ctx.saved_tensors
        if g_uv is None and g_depth is None and g_n is None:
            return None, None, None, None, None, None
        ncol = 7 if g_n is not None else (4 if g_depth is not None else 3)
        P = idx.shape[0]
        rows = vals.new_zeros(3, ncol, P)  # (coef, column, pixel): index_add along the last dim is fast
        gN = rows[0]
        gs = gN[0]
        for lo, hi, gg in ((1, 3, g_uv), (3, 4, g_depth), (4, 7, g_n)):
            if gg is None:
                continue
            torch.mul(gg.reshape(hi - lo, -1), inv_s, out=gN[lo:hi])
            for k in range(lo, hi):
                gs.addcmul_(gN[k], vals[k - 1], value=-1.0)
        torch.mul(gN, dx, out=rows[1])
        torch.mul(gN, dy, out=rows[2])
        acc = rows.new_zeros(3, ncol, ctx.m).index_add_(2, idx, rows)
        g_table = rows.new_zeros(ctx.m, 2 + 3 * _NP)
        g_table[:, 2:].view(ctx.m, 3, _NP)[:, :, :ncol] = acc.permute(2, 0, 1)
        return g_table, None, None, None, None, None


def plane_interp(table: torch.Tensor, idx: torch.Tensor, nx: torch.Tensor, ny: torch.Tensor, H: int, W: int):
    """Evaluate a plane_table at P pixels (row idx of the table, NDC nx, ny), structure-of-arrays:
    uv (2, P), depth (P,), normal (3, P) (differentiable w.r.t. the table), bw (2, P), z/w (P,),
    uv_da (4, P) (no gradient)."""
    return _PlaneFn.apply(table, idx, nx, ny, H, W)



def render_cloth_fused(vertices, pos, tri, uv, tex, H, W, max_mip_level, shading=None) -> RenderOutput:
    """The same pipeline on the covered pixels only: one per-triangle table of plane coefficients
    (plane_table) evaluated per pixel with a hand-written backward, texture on the covered pixels, and
    dense images only at the end; identical in value to the primitive pipeline (tested). shading: None or
    (B, V, 3) per-vertex factors, interpolated in the normals' columns and multiplied into the colour."""
    B, V, _ = vertices.shape
    T = tri.shape[0]
    n_pix = B * H * W
    pix, tid = visibility(pos, tri, (H, W))
    with torch.no_grad():
        if B == 1:
            row_idx = tid
            rem = pix
        else:
            b = torch.div(pix, H * W, rounding_mode="floor")
            row_idx = b * T + tid
            rem = pix - b * (H * W)
        prow = torch.div(rem, W, rounding_mode="floor")
        nx, ny = (2.0 * torch.stack([rem - prow * W, prow]).to(pos.dtype) + 1.0) / const((W, H), pos).view(2, 1) - 1.0
    uv_tex = torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1)
    normals_v = vertex_normals(vertices, tri) if shading is None else shading
    table = plane_table(pos, tri, uv_tex, normals_v)
    uv_pix, depth_c, n, bw, zw, uv_da = plane_interp(table, row_idx, nx, ny, H, W)
    rgb_c = texture_fast(tex, uv_pix[0], uv_pix[1], uv_da, max_mip_level=max_mip_level)
    if shading is not None:
        rgb_c = rgb_c.to(n.dtype) * n
    rgb_img = ScatterPlanar.apply(rgb_c.to(pos.dtype), pix, n_pix).reshape(B, H, W, 3)
    cov_img = pos.new_zeros(n_pix).index_fill_(0, pix, 1.0).reshape(B, H, W)  # coverage, no gradient
    with torch.no_grad():
        tid_img = torch.full((n_pix,), -1, dtype=torch.long, device=pos.device).index_copy_(0, pix, tid)
        depth_img = torch.full((n_pix,), math.inf, dtype=pos.dtype, device=pos.device).index_copy_(0, pix, zw)
    rgb, mask = antialias_core((rgb_img, cov_img), tid_img.reshape(B, H, W), depth_img.reshape(B, H, W),
                                  pos, tri, split=True)
    depth = scatter_rows(depth_c, pix, n_pix).reshape(B, H, W)

    def normals_image() -> torch.Tensor:   # made only when read (the shape phase does not)
        nn = n / (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().clamp_min(1e-12)  # (3, P): no dim-0 norm
        return scatter_rows(nn.T, pix, n_pix).reshape(B, H, W, 3)

    def rast_image() -> torch.Tensor:
        with torch.no_grad():
            return pos.new_zeros(n_pix, 4).index_copy_(
                0, pix, torch.stack([bw[0], bw[1], zw, (tid + 1).to(pos.dtype)], dim=-1)).reshape(B, H, W, 4)

    return RenderOutput(rgb=rgb, mask=mask, depth=depth, normals=normals_image if shading is None else no_normals,
                        rast=rast_image, pos_clip=pos)
