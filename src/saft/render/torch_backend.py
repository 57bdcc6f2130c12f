"""The PyTorch rasterizer: nvdiffrast's four primitives in vectorised torch, for any device.

Layout of the work (all batched, no Python loop over triangles or pixels):

* visibility (no autograd): per triangle, the pixel rows its screen bounding box covers; per
  (triangle, row) the exact span of pixel centres inside the triangle from its three edge functions; the
  spans are expanded into (pixel, depth, triangle) candidates and the nearest one per pixel wins through
  one ``scatter_reduce(amin)`` on an int64 key (quantised z/w << 32 | triangle id). Pixel centres on an
  edge shared by two triangles are covered by both (inclusive test with a 1e-4 px margin), so a mesh
  never shows cracks; the depth test (ties → lower triangle id) picks one.
* barycentrics (autograd): only for covered pixels, perspective-correct, straight from the clip-space
  positions, so gradients reach the vertex positions as in nvdiffrast.
* interpolate / texture (autograd): gathers on the covered pixels only; texture is bilinear with
  trilinear mip-mapping (``torch.nn.functional.grid_sample`` per level on the pixels that use it).
* render_cloth's path (cloth._render_cloth_torch) uses the compact kernels at the end of this file:
  plane_table / plane_interp (barycentrics, attributes and their screen derivatives as ratios of affine
  functions of the pixel position: one per-triangle row of plane coefficients, one gather per pixel, one
  index_add in the backward) and texture_fast (clamp-mode trilinear lookup, structure-of-arrays, level 0
  in the caller's HWC layout); equal to the primitives above in value and gradient (tested).
  On CPU, small-dimension reductions, advanced indexing and strided (transposing) copies are several
  times slower than contiguous elementwise ops and 1-D index_select/index_add: the kernels avoid them.
* antialias: nvdiffrast's analytic scheme — for each pair of horizontally or vertically adjacent pixels
  with different triangles, a silhouette edge (mesh boundary, or an edge between a front- and a back-facing
  triangle: folds) of the nearer triangle that crosses the segment between the two centres blends the
  colours in proportion to where it crosses; the blend weight depends on the edge's projected end points,
  which gives the silhouette gradients with respect to the positions.

Conventions follow nvdiffrast (see ``saft.render``): rast (B, H, W, 4) = (u, v, z/w, triangle_id + 1),
an attribute interpolates as u·a0 + v·a1 + (1 − u − v)·a2; row r of the output is at y_ndc = (2r+1)/H − 1.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from saft.render.topology import edge_neighbors

_EDGE_EPS = 1e-4  # pixels: pixel centres this close outside a triangle still count as covered
_W_EPS = 1e-9  # triangles with a vertex at w ≤ this (at or behind the eye) are discarded
_INT64_MAX = torch.iinfo(torch.int64).max


def _check_pos_tri(pos: torch.Tensor, tri: torch.Tensor):
    if pos.dim() == 2:
        pos = pos[None]
    if pos.dim() != 3 or pos.shape[-1] != 4:
        raise ValueError(f"pos must be (B, V, 4) clip-space positions, got {tuple(pos.shape)}")
    if tri.dim() != 2 or tri.shape[-1] != 3:
        raise ValueError(f"tri must be (T, 3), got {tuple(tri.shape)}")
    return pos, tri.to(device=pos.device, dtype=torch.int64)


# ------------------------------------------------------------------------------------------ visibility
@torch.no_grad()
def visibility(pos: torch.Tensor, tri: torch.Tensor, resolution: tuple[int, int]):
    """Discrete part of rasterization: (pix, tid), the flat index b·H·W + row·W + col of every covered
    pixel (ascending) and the index of the triangle seen there. No autograd.

    Structure-of-arrays throughout (per-vertex / per-edge quantities are separate contiguous rows, the
    three-way minima and maxima explicit, gathers by index_select): small-dimension reductions and
    advanced indexing are several times slower on CPU."""
    pos, tri = _check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B, V, _ = pos.shape
    T = tri.shape[0]
    dev = pos.device
    g = pos.detach().permute(2, 0, 1).index_select(2, tri.T.reshape(-1)).reshape(4, B, 3, T)
    w = g[3]  # (B, 3 vertices, T)
    okw = w > _W_EPS
    ok = okw[:, 0] & okw[:, 1] & okw[:, 2]
    w = torch.where(okw, w, torch.ones_like(w))
    x = (g[0] / w + 1.0) * (0.5 * W) - 0.5  # pixel units, centre of column j at x = j
    y = (g[1] / w + 1.0) * (0.5 * H) - 0.5
    z = g[2] / w
    # edge function k (opposite vertex k, from vertex k+1 to k+2): e_k = A x + B y + C, e_k(vertex k) = 2·area
    xi, yi = x.roll(-1, 1), y.roll(-1, 1)
    xj, yj = x.roll(-2, 1), y.roll(-2, 1)
    A = yi - yj
    Bc = xj - xi
    C = -(A * xi + Bc * yi)
    area2 = A[:, 0] * x[:, 0] + Bc[:, 0] * y[:, 0] + C[:, 0]
    ok &= area2.abs() > 1e-12
    zlo, zhi = z < -1, z > 1
    ok &= ~((zlo[:, 0] & zlo[:, 1] & zlo[:, 2]) | (zhi[:, 0] & zhi[:, 1] & zhi[:, 2]))
    s = torch.where(area2 < 0, -1.0, 1.0).to(x.dtype)[:, None]
    A, Bc, C = A * s, Bc * s, C * s
    inv_area = 1.0 / area2.abs().clamp_min(1e-30)

    def sum3(t):
        return t[:, 0] + t[:, 1] + t[:, 2]

    def min3(t):
        return torch.minimum(torch.minimum(t[:, 0], t[:, 1]), t[:, 2])

    def max3(t):
        return torch.maximum(torch.maximum(t[:, 0], t[:, 1]), t[:, 2])

    zA = sum3(A * z) * inv_area  # z/w is affine in screen space
    zB = sum3(Bc * z) * inv_area
    zC = sum3(C * z) * inv_area
    ymin = torch.ceil(min3(y) - _EDGE_EPS).clamp(min=0)
    ymax = torch.floor(max3(y) + _EDGE_EPS).clamp(max=H - 1)
    xmin = torch.ceil(min3(x) - _EDGE_EPS).clamp(min=0)
    xmax = torch.floor(max3(x) + _EDGE_EPS).clamp(max=W - 1)
    nrows = (ymax - ymin + 1).clamp(min=0)
    nrows = torch.where(ok & (xmax >= xmin), nrows, torch.zeros_like(nrows)).long().reshape(-1)

    inst = torch.nonzero(nrows > 0).squeeze(1)  # over B·T
    if inst.numel() == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    cnt = nrows.index_select(0, inst)
    R = int(cnt.sum())
    pair_inst = torch.repeat_interleave(inst, cnt, output_size=R)
    start = torch.cumsum(cnt, 0) - cnt
    row = ymin.reshape(-1).index_select(0, pair_inst) + (
        torch.arange(R, device=dev) - torch.repeat_interleave(start, cnt, output_size=R)).to(x.dtype)

    def per_row(t):  # (B, 3, T) → (3, R)
        return t.permute(1, 0, 2).reshape(3, B * T).index_select(1, pair_inst)

    Ai, Bi, Ci = per_row(A), per_row(Bc), per_row(C)
    num = -(Bi * row + Ci)  # inside ⇔ A x ≥ num for all three edges
    safeA = torch.where(Ai == 0, torch.ones_like(Ai), Ai)
    bound = num / safeA
    inf = torch.full_like(bound, math.inf)
    lo_k = torch.where(Ai > 0, bound, -inf)
    hi_k = torch.where(Ai < 0, bound, inf)
    lo = torch.maximum(torch.maximum(lo_k[0], lo_k[1]), lo_k[2])
    hi = torch.minimum(torch.minimum(hi_k[0], hi_k[1]), hi_k[2])
    bad = (Ai == 0) & (num > _EDGE_EPS * Bi.abs())
    flat_bad = bad[0] | bad[1] | bad[2]
    xl = torch.ceil(lo - _EDGE_EPS).clamp(min=0)
    xr = torch.floor(hi + _EDGE_EPS).clamp(max=W - 1)
    span = (xr - xl + 1).clamp(min=0)
    span = torch.where(flat_bad, torch.zeros_like(span), span).long()
    keep = torch.nonzero(span > 0).squeeze(1)
    span, xl, row, pair_inst = (t.index_select(0, keep) for t in (span, xl, row, pair_inst))
    N = int(span.sum())
    if N == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    pair = torch.repeat_interleave(torch.arange(span.numel(), device=dev), span, output_size=N)
    pstart = torch.cumsum(span, 0) - span
    # column of each candidate: xl of its span plus its offset in the span
    px = torch.arange(N, device=dev) + (xl.long() - pstart).index_select(0, pair)
    inst_p = pair_inst.index_select(0, pair)
    zrow = zB.reshape(-1).index_select(0, pair_inst) * row + zC.reshape(-1).index_select(0, pair_inst)
    zpix = zrow.index_select(0, pair) + zA.reshape(-1).index_select(0, inst_p) * px.to(x.dtype)
    if B == 1:
        tid = inst_p
        pix = (row.long() * W).index_select(0, pair) + px
    else:
        b = torch.div(inst_p, T, rounding_mode="floor")
        tid = inst_p - b * T
        pix = ((b * H) * W + (row.long() * W).index_select(0, pair)) + px
    inside = (zpix >= -1.0) & (zpix <= 1.0)
    q = ((zpix.clamp(-1.0, 1.0) + 1.0) * float(2 ** 29)).long()  # 31 bits of depth
    key = (q << 32) | tid
    if not bool(inside.all()):
        key = torch.where(inside, key, torch.full_like(key, _INT64_MAX))
    zbuf = torch.full((B * H * W,), _INT64_MAX, dtype=torch.int64, device=dev)
    zbuf.scatter_reduce_(0, pix, key, reduce="amin", include_self=True)
    pix_out = torch.nonzero(zbuf != _INT64_MAX).squeeze(1)
    tid_out = zbuf.index_select(0, pix_out) & 0xFFFFFFFF
    return pix_out, tid_out


def _pixel_ndc(pix: torch.Tensor, H: int, W: int, dtype):
    rem = pix % (H * W)
    row = torch.div(rem, W, rounding_mode="floor")
    col = rem - row * W
    return (2.0 * col.to(dtype) + 1.0) / W - 1.0, (2.0 * row.to(dtype) + 1.0) / H - 1.0


def barycentrics(pos: torch.Tensor, tri: torch.Tensor, pix: torch.Tensor, tid: torch.Tensor,
                 resolution: tuple[int, int], with_db: bool = False):
    """Perspective-correct (u, v, z/w) at the centres of pixels `pix` seen through triangles `tid`:
    (P, 3), differentiable with respect to `pos`. With with_db also (P, 4) = (du/dX, du/dY, dv/dX, dv/dY)
    in pixel units (no gradient)."""
    bw, zw, db = bary_weights(pos, tri, pix, tid, resolution, with_db=with_db)
    out = torch.stack([bw[0], bw[1], zw], dim=-1)
    return (out, db.T) if with_db else out


def pixel_vertex_ids(pos: torch.Tensor, tri: torch.Tensor, pix: torch.Tensor, tid: torch.Tensor, H: int, W: int):
    """(3, P) indices into pos.reshape(-1, 4) of the three vertices seen at each covered pixel."""
    V = pos.shape[1]
    b = torch.div(pix, H * W, rounding_mode="floor")
    return tri[tid].T + b * V


def bary_weights(pos: torch.Tensor, tri: torch.Tensor, pix: torch.Tensor, tid: torch.Tensor,
                 resolution: tuple[int, int], with_db: bool = False, vid: torch.Tensor | None = None):
    """Structure-of-arrays barycentrics: bw (3, P) perspective-correct weights of the triangle's vertices,
    zw (P,) = z/w, both differentiable w.r.t. pos (hand-written backward); db (4, P) = (db0/dX, db0/dY,
    db1/dX, db1/dY) in pixel units without gradient, or None."""
    H, W = int(resolution[0]), int(resolution[1])
    ndc_x, ndc_y = _pixel_ndc(pix, H, W, pos.dtype)
    if vid is None:
        vid = pixel_vertex_ids(pos, tri, pix, tid, H, W)
    bw, zw, db = _BaryFn.apply(pos.reshape(-1, 4), vid, ndc_x, ndc_y, with_db, H, W)
    return bw, zw, db


def _bary_terms(pf, vid, nx, ny):
    g = pf.T.contiguous().index_select(1, vid.reshape(-1)).reshape(4, 3, -1)  # coordinate, vertex, pixel
    x, y, z, w = g[0], g[1], g[2], g[3]
    X = x - nx * w
    Y = y - ny * w
    c = torch.stack([X[1] * Y[2] - X[2] * Y[1], X[2] * Y[0] - X[0] * Y[2], X[0] * Y[1] - X[1] * Y[0]])
    return z, w, X, Y, c


class _BaryFn(torch.autograd.Function):
    """Barycentrics from the clip-space vertices, structure-of-arrays with a hand-written backward (the
    autograd graph of the same expression is several times slower on CPU)."""

    @staticmethod
    def forward(ctx, pf, vid, nx, ny, with_db, H, W):
        z, w, X, Y, c = _bary_terms(pf, vid, nx, ny)
        s = c[0] + c[1] + c[2]
        inv_s = 1.0 / torch.where(s == 0, torch.ones_like(s), s)
        bw = c * inv_s
        cz = (c * z).sum(0)
        cw = (c * w).sum(0)
        inv_cw = 1.0 / torch.where(cw == 0, torch.ones_like(cw), cw)
        zw = cz * inv_cw
        db = None
        if with_db:
            dcx = torch.stack([-(w[1] * Y[2] - w[2] * Y[1]), -(w[2] * Y[0] - w[0] * Y[2])])
            dcy = torch.stack([-(X[1] * w[2] - X[2] * w[1]), -(X[2] * w[0] - X[0] * w[2])])
            dsx = -(w[1] * Y[2] - w[2] * Y[1]) - (w[2] * Y[0] - w[0] * Y[2]) - (w[0] * Y[1] - w[1] * Y[0])
            dsy = -(X[1] * w[2] - X[2] * w[1]) - (X[2] * w[0] - X[0] * w[2]) - (X[0] * w[1] - X[1] * w[0])
            dbx = (dcx - bw[:2] * dsx) * inv_s * (2.0 / W)
            dby = (dcy - bw[:2] * dsy) * inv_s * (2.0 / H)
            db = torch.stack([dbx[0], dby[0], dbx[1], dby[1]])
            ctx.mark_non_differentiable(db)
        ctx.save_for_backward(vid, nx, ny, z, w, X, Y, c)
        ctx.n = pf.shape[0]
        return bw, zw, db

    @staticmethod
    def backward(ctx, g_bw, g_zw, g_db):
        vid, nx, ny, z, w, X, Y, c = ctx.saved_tensors
        s = c[0] + c[1] + c[2]
        inv_s = 1.0 / torch.where(s == 0, torch.ones_like(s), s)
        bw = c * inv_s
        if g_bw is None:
            g_bw = torch.zeros_like(c)
        gc = (g_bw - (g_bw * bw).sum(0)) * inv_s
        gx = torch.zeros_like(c)
        if g_zw is not None:
            cw = (c * w).sum(0)
            inv_cw = 1.0 / torch.where(cw == 0, torch.ones_like(cw), cw)
            q = (c * z).sum(0) * inv_cw
            gcz = g_zw * inv_cw
            gcw = -gcz * q
            gc = gc + gcz * z + gcw * w
            g_z = gcz * c
            g_w = gcw * c
        else:
            g_z = torch.zeros_like(c)
            g_w = torch.zeros_like(c)
        gX = torch.stack([gc[2] * Y[1] - gc[1] * Y[2], gc[0] * Y[2] - gc[2] * Y[0], gc[1] * Y[0] - gc[0] * Y[1]])
        gY = torch.stack([gc[1] * X[2] - gc[2] * X[1], gc[2] * X[0] - gc[0] * X[2], gc[0] * X[1] - gc[1] * X[0]])
        g_w = g_w - gX * nx - gY * ny
        gP = torch.stack([gX, gY, g_z, g_w], dim=-1)  # (3, P, 4)
        gpf = gP.new_zeros(ctx.n, 4).index_add_(0, vid.reshape(-1), gP.reshape(-1, 4))
        return gpf, None, None, None, None, None, None


def rasterize(pos: torch.Tensor, tri: torch.Tensor, resolution, with_db: bool = False):
    """nvdiffrast-style rasterize: rast (B, H, W, 4) = (u, v, z/w, triangle_id + 1); zeros where empty.
    u, v, z/w are differentiable with respect to pos. with_db=True returns (rast, rast_db), rast_db
    (B, H, W, 4) = (du/dX, du/dY, dv/dX, dv/dY) in pixel units (no gradient), for mip-mapping."""
    pos, tri = _check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B = pos.shape[0]
    pix, tid = visibility(pos, tri, (H, W))
    res = barycentrics(pos, tri, pix, tid, (H, W), with_db=with_db)
    uvz, db = res if with_db else (res, None)
    vals = torch.cat([uvz, (tid + 1).to(pos.dtype)[:, None]], dim=-1)
    rast = _scatter_rows(vals, pix, B * H * W).reshape(B, H, W, 4)
    if not with_db:
        return rast
    rast_db = torch.zeros(B * H * W, 4, dtype=pos.dtype, device=pos.device)
    rast_db[pix] = db
    return rast, rast_db.reshape(B, H, W, 4)


class _ScatterRows(torch.autograd.Function):
    """out = zeros(n, C); out[idx] = vals — with a gather as backward (idx unique)."""

    @staticmethod
    def forward(ctx, vals, idx, n):
        out = vals.new_zeros((n,) + tuple(vals.shape[1:]))
        out.index_copy_(0, idx, vals)
        ctx.save_for_backward(idx)
        return out

    @staticmethod
    def backward(ctx, g):
        (idx,) = ctx.saved_tensors
        return g.index_select(0, idx), None, None


def _scatter_rows(vals, idx, n):
    return _ScatterRows.apply(vals, idx, n)


def _covered(rast: torch.Tensor):
    """(pix, tid) of the covered pixels of a rast tensor."""
    flat = rast.detach().reshape(-1, 4)[:, 3]
    pix = torch.nonzero(flat > 0).squeeze(1)
    return pix, flat[pix].long() - 1


# ------------------------------------------------------------------------------------------ interpolate
def interpolate(attr: torch.Tensor, rast: torch.Tensor, tri: torch.Tensor, rast_db=None, diff_attrs=None):
    """Vertex attributes (B or 1, V, C) or (V, C) → pixels (B, H, W, C): u·a0 + v·a1 + (1−u−v)·a2, zeros
    where empty. Differentiable w.r.t. attr and rast. With rast_db (from rasterize(..., with_db=True))
    also returns the screen-space derivatives of the attributes listed in diff_attrs ('all' or a list of
    channel indices) as (B, H, W, 2·n) = (dA/dX, dA/dY) per attribute (no gradient): (out, out_da)."""
    B, H, W, _ = rast.shape
    if attr.dim() == 2:
        attr = attr[None]
    tri = tri.to(device=rast.device, dtype=torch.int64)
    V, C = attr.shape[1], attr.shape[2]
    pix, tid = _covered(rast)
    r = _gather_rows(rast.reshape(-1, 4), pix)
    vid = tri[tid]
    if attr.shape[0] == 1:
        a = attr[0][vid]  # (P, 3, C)
    else:
        b = torch.div(pix, H * W, rounding_mode="floor")
        a = attr.reshape(-1, C)[vid + (b * V)[:, None]]
    u, v = r[:, 0:1], r[:, 1:2]
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    vals = a2 + u * (a0 - a2) + v * (a1 - a2)
    out = _scatter_rows(vals, pix, B * H * W).reshape(B, H, W, C)
    if rast_db is None:
        return out
    if diff_attrs is None:
        return out, None
    idx = list(range(C)) if diff_attrs == "all" else list(diff_attrs)
    with torch.no_grad():
        db = rast_db.reshape(-1, 4)[pix]
        d0 = (a0 - a2)[:, idx].detach()
        d1 = (a1 - a2)[:, idx].detach()
        dx = d0 * db[:, 0:1] + d1 * db[:, 2:3]
        dy = d0 * db[:, 1:2] + d1 * db[:, 3:4]
        da = torch.stack([dx, dy], dim=-1).reshape(-1, 2 * len(idx))
        out_da = rast.new_zeros(B * H * W, 2 * len(idx))
        out_da[pix] = da
    return out, out_da.reshape(B, H, W, 2 * len(idx))


class _GatherRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, idx):
        ctx.save_for_backward(idx)
        ctx.n = x.shape[0]
        return x.index_select(0, idx)

    @staticmethod
    def backward(ctx, g):
        (idx,) = ctx.saved_tensors
        out = g.new_zeros(ctx.n, g.shape[1])
        out.index_copy_(0, idx, g)  # idx unique
        return out, None


def _gather_rows(x, idx):
    return _GatherRows.apply(x, idx)


# ------------------------------------------------------------------------------------------ texture
def mip_pyramid(tex_nchw: torch.Tensor, max_mip_level: int | None = None) -> list[torch.Tensor]:
    """Box-filtered mip levels (differentiable), level 0 first, down to 1×1 or max_mip_level."""
    levels = [tex_nchw]
    while True:
        h, w = levels[-1].shape[-2:]
        if (h == 1 and w == 1) or (max_mip_level is not None and len(levels) > max_mip_level):
            break
        t = levels[-1]
        if h % 2 == 0 and w % 2 == 0:
            levels.append(F.avg_pool2d(t, 2))
        else:
            levels.append(F.interpolate(t, size=(max(1, h // 2), max(1, w // 2)), mode="area"))
    return levels


def _sample(t: torch.Tensor, uv: torch.Tensor, boundary_mode: str) -> torch.Tensor:
    """Bilinear lookup of t (1, C, h, w) at uv (N, 2) (u → column, v → row, texel centres at
    (i + 0.5)/size) → (N, C)."""
    h, w = t.shape[-2:]
    if boundary_mode == "wrap":
        tp = F.pad(t, (1, 1, 1, 1), mode="circular")
        fu = uv[:, 0] - torch.floor(uv[:, 0])
        fv = uv[:, 1] - torch.floor(uv[:, 1])
        gx = (fu * w + 1.0) / (w + 2) * 2.0 - 1.0
        gy = (fv * h + 1.0) / (h + 2) * 2.0 - 1.0
        grid = torch.stack([gx, gy], dim=-1)
        t = tp
        pad = "border"
    elif boundary_mode == "clamp":
        grid = uv * 2.0 - 1.0
        pad = "border"
    elif boundary_mode == "zero":
        grid = uv * 2.0 - 1.0
        pad = "zeros"
    else:
        raise ValueError(f"unknown boundary_mode {boundary_mode!r} (wrap, clamp, zero)")
    out = F.grid_sample(t, grid.reshape(1, 1, -1, 2).to(t.dtype), mode="bilinear", padding_mode=pad,
                        align_corners=False)
    return out[0, :, 0].T


def texture(tex: torch.Tensor, uv: torch.Tensor, uv_da: torch.Tensor | None = None, filter_mode: str = "auto",
            boundary_mode: str = "wrap", max_mip_level: int | None = None, mask: torch.Tensor | None = None):
    """nvdiffrast-style texture lookup: tex (B or 1, Ht, Wt, C) or (Ht, Wt, C), uv (B, H, W, 2) with
    u → column and v → row (row 0 at v = 0, texel centres at (i + 0.5)/size) → (B, H, W, C).

    filter_mode: 'linear' (bilinear), 'linear-mipmap-linear' (trilinear over a box-filtered pyramid; the
    level from uv_da = (du/dX, du/dY, dv/dX, dv/dY), as interpolate returns it), 'auto' (mip-mapped when
    uv_da is given). Differentiable w.r.t. tex and uv (not uv_da). mask (B, H, W) bool, torch backend
    only: pixels to look up (others get 0) — the renderer passes the coverage to skip the background.
    """
    if tex.dim() == 3:
        tex = tex[None]
    B, H, W, _ = uv.shape
    C = tex.shape[-1]
    if filter_mode == "auto":
        filter_mode = "linear-mipmap-linear" if uv_da is not None else "linear"
    if filter_mode not in ("linear", "linear-mipmap-linear", "nearest"):
        raise ValueError(f"unsupported filter_mode {filter_mode!r}")
    if filter_mode == "linear-mipmap-linear" and uv_da is None:
        raise ValueError("filter_mode='linear-mipmap-linear' needs uv_da")
    if tex.shape[0] not in (1, B):
        raise ValueError(f"texture batch {tex.shape[0]} does not match uv batch {B}")
    if tex.shape[0] > 1:  # per-image textures: one lookup per image
        outs = [texture(tex[i:i + 1], uv[i:i + 1], None if uv_da is None else uv_da[i:i + 1], filter_mode,
                        boundary_mode, max_mip_level, None if mask is None else mask[i:i + 1])
                for i in range(B)]
        return torch.cat(outs, dim=0)
    uvf = uv.reshape(-1, 2)
    daf = None if uv_da is None or filter_mode != "linear-mipmap-linear" else uv_da.reshape(-1, 4)
    sel_all = None
    if mask is not None:
        sel_all = torch.nonzero(mask.reshape(-1)).squeeze(1)
        uvf = uvf.index_select(0, sel_all)
        daf = None if daf is None else daf.index_select(0, sel_all)
    if filter_mode == "nearest":
        Ht, Wt = tex.shape[1:3]
        col = (uvf[:, 0] * Wt).floor().long().clamp(0, Wt - 1)
        row = (uvf[:, 1] * Ht).floor().long().clamp(0, Ht - 1)
        vals = tex[0][row, col]
    else:
        vals = texture_compact(tex[0], uvf, daf, boundary_mode, max_mip_level)
    if sel_all is not None:
        return _scatter_rows(vals, sel_all, B * H * W).reshape(B, H, W, C)
    return vals.reshape(B, H, W, C)


# ------------------------------------------------------------------------------------------ antialias
def _screen_xy(pos: torch.Tensor, H: int, W: int):
    w = pos[..., 3]
    w = torch.where(w.abs() < _W_EPS, torch.full_like(w, _W_EPS), w)
    return (pos[..., 0] / w + 1.0) * (0.5 * W) - 0.5, (pos[..., 1] / w + 1.0) * (0.5 * H) - 0.5


def silhouette_edges(pos: torch.Tensor, tri: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(B, T, 3) bool: edge k of triangle t (tri[t, k] → tri[t, (k+1)%3]) is a silhouette edge in image b:
    on the mesh boundary, or shared with a triangle facing the other way in screen space (a fold)."""
    with torch.no_grad():
        nbr = edge_neighbors(tri)
        x, y = _screen_xy(pos.detach(), H, W)
        xt, yt = x[:, tri], y[:, tri]  # (B, T, 3)
        area = (xt[..., 1] - xt[..., 0]) * (yt[..., 2] - yt[..., 0]) - (xt[..., 2] - xt[..., 0]) * (yt[..., 1] - yt[..., 0])
        front = area > 0
        nb = nbr.clamp(min=0)
        return (nbr[None] < 0) | (front[:, nb] != front[..., None])


def antialias(color: torch.Tensor, rast: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """nvdiffrast-style analytic antialiasing of color (B, H, W, C); differentiable w.r.t. color and, through
    the blend weights, pos (silhouette gradients on boundary and fold edges)."""
    with torch.no_grad():
        tidf = rast.detach()[..., 3]
        tid_img = tidf.long() - 1
        depth_img = torch.where(tidf > 0, rast.detach()[..., 2], torch.full_like(tidf, math.inf))
    return _antialias_impl(color, tid_img, depth_img, pos, tri)


def _antialias_impl(color, tid_img, depth_img, pos, tri, split=False):
    pos, tri = _check_pos_tri(pos, tri)
    if split:  # color = (channels (B, H, W, C−1), last channel (B, H, W)) as separate tensors
        B, H, W, C = color[0].shape[:3] + (color[0].shape[3] + 1,)
    else:
        B, H, W, C = color.shape
    V = pos.shape[1]
    T = tri.shape[0]
    with torch.no_grad():
        sil = silhouette_edges(pos, tri, H, W)  # (B, T, 3)
        silT = sil.reshape(-1, 3).T.contiguous()  # (3, B·T)
        tri_sil = silT[0] | silT[1] | silT[2]  # (B·T,)
        triT = tri.T.contiguous()
        x, y = _screen_xy(pos.detach(), H, W)  # (B, V)
        xf, yf = x.reshape(-1), y.reshape(-1)
        tflat = tid_img.reshape(-1)
        dflat = depth_img.reshape(-1)
        pairs = []
        for axis in (0, 1):  # 0: horizontal neighbours (j, j+1), 1: vertical (i, i+1)
            if axis == 0:
                if W < 2:
                    continue
                diff = tid_img[:, :, :-1] != tid_img[:, :, 1:]
                a_idx = torch.nonzero(diff.reshape(-1)).squeeze(1)
                pa = a_idx + torch.div(a_idx, W - 1, rounding_mode="floor")  # (b·H + i)·W + j
                pb = pa + 1
            else:
                if H < 2:
                    continue
                diff = tid_img[:, :-1, :] != tid_img[:, 1:, :]
                a_idx = torch.nonzero(diff.reshape(-1)).squeeze(1)
                pa = a_idx + torch.div(a_idx, (H - 1) * W, rounding_mode="floor") * W
                pb = pa + W
            a_front = dflat.index_select(0, pa) <= dflat.index_select(0, pb)
            pf = torch.where(a_front, pa, pb)  # the nearer pixel
            po = torch.where(a_front, pb, pa)
            t_f = tflat.index_select(0, pf)
            bf = torch.div(pf, H * W, rounding_mode="floor") if B > 1 else torch.zeros_like(pf)
            keep = torch.nonzero(tri_sil.index_select(0, bf * T + t_f)).squeeze(1)  # triangles with a silhouette edge
            pf, po, t_f, bf = (t.index_select(0, keep) for t in (pf, po, t_f, bf))
            # structure-of-arrays over the three edges k (vertex k → k+1) of the front triangle
            bt = t_f if B == 1 else bf * T + t_f
            vk = [triT[k].index_select(0, t_f) for k in range(3)]
            if B > 1:
                vk = [v + bf * V for v in vk]
            xk = [xf.index_select(0, v) for v in vk]
            yk = [yf.index_select(0, v) for v in vk]
            rem_f = pf if B == 1 else pf - bf * H * W
            fi_l = torch.div(rem_f, W, rounding_mode="floor")
            fi = fi_l.to(x.dtype)
            fj = (rem_f - fi_l * W).to(x.dtype)
            sgn = torch.where(po > pf, 1.0, -1.0).to(x.dtype)
            has = k_first = None
            for k in range(3):
                x0, y0, x1, y1 = xk[k], yk[k], xk[(k + 1) % 3], yk[(k + 1) % 3]
                dx, dy = x1 - x0, y1 - y0
                if axis == 0:  # crossing of row fi, edges more vertical than horizontal
                    major = (dy.abs() >= dx.abs()) & (dy != 0)
                    tpar = (fi - y0) / torch.where(dy == 0, torch.ones_like(dy), dy)
                    tt = (x0 + tpar * dx - fj) * sgn
                else:  # crossing of column fj, edges more horizontal than vertical
                    major = dx.abs() > dy.abs()
                    tpar = (fj - x0) / torch.where(dx == 0, torch.ones_like(dx), dx)
                    tt = (y0 + tpar * dy - fi) * sgn
                ok = silT[k].index_select(0, bt) & major
                ok &= (tpar >= 0) & (tpar <= 1) & (tt >= 0) & (tt <= 1)
                if has is None:
                    has, k_first = ok, torch.zeros_like(vk[0])
                else:  # the first edge that qualifies (as argmax over k)
                    k_first = torch.where(has, k_first, torch.full_like(k_first, k))
                    has = has | ok
            sel = torch.nonzero(has).squeeze(1)
            if sel.numel():
                ks = k_first.index_select(0, sel)
                v_s = [v.index_select(0, sel) for v in vk]
                e0 = torch.where(ks == 0, v_s[0], torch.where(ks == 1, v_s[1], v_s[2]))
                e1 = torch.where(ks == 0, v_s[1], torch.where(ks == 1, v_s[2], v_s[0]))
                pairs.append((axis, pf.index_select(0, sel), po.index_select(0, sel), e0, e1,
                              fi.index_select(0, sel), fj.index_select(0, sel), sgn.index_select(0, sel)))
    if not pairs:
        return color
    posf = pos.reshape(-1, 4)
    fs, pfs, pos_, tgts = [], [], [], []
    for axis, pf, po, e0, e1, fi, fj, sgn in pairs:
        xe0, ye0 = _screen_xy(posf.index_select(0, e0), H, W)
        xe1, ye1 = _screen_xy(posf.index_select(0, e1), H, W)
        if axis == 0:
            tt = (xe0 + (fi - ye0) / (ye1 - ye0) * (xe1 - xe0) - fj) * sgn
        else:
            tt = (ye0 + (fj - xe0) / (xe1 - xe0) * (ye1 - ye0) - fi) * sgn
        f = tt - 0.5  # > 0: the front triangle reaches into the other pixel; < 0: it leaves part of its own
        fs.append(f)
        pfs.append(pf)
        pos_.append(po)
        tgts.append(torch.where(f.detach() > 0, po, pf))
    dt = color[0].dtype if split else color.dtype
    args = (torch.cat(fs).to(dt), torch.cat(pfs), torch.cat(pos_), torch.cat(tgts))
    if split:
        rgb, last = _AABlendSplitFn.apply(color[0].reshape(-1, C - 1), color[1].reshape(-1), *args)
        return rgb.reshape(B, H, W, C - 1), last.reshape(B, H, W)
    return _AABlendFn.apply(color.reshape(-1, C), *args).reshape(B, H, W, C)


class _AABlendFn(torch.autograd.Function):
    """out = color; out[target] += f · (color[pf] − color[po]) (targets unique per axis, may repeat across
    the two axes), with a backward that touches only the blended rows (autograd of the indexing would
    build dense zero images per gather)."""

    @staticmethod
    def forward(ctx, color, f, pf, po, target):
        d = color.index_select(0, pf) - color.index_select(0, po)  # (K, C)
        out = color.clone().index_add_(0, target, d * f[:, None])
        ctx.save_for_backward(f, pf, po, target, d)
        return out

    @staticmethod
    def backward(ctx, g):
        f, pf, po, target, d = ctx.saved_tensors
        g_t = g.index_select(0, target)  # (K, C)
        g_f = None
        if ctx.needs_input_grad[1]:
            prod = g_t * d
            g_f = prod[:, 0]
            for c in range(1, prod.shape[1]):
                g_f = g_f + prod[:, c]
        g_color = None
        if ctx.needs_input_grad[0]:
            gd = g_t * f[:, None]
            g_color = g.clone().index_add_(0, pf, gd).index_add_(0, po, gd, alpha=-1)
        return g_color, g_f, None, None, None


class _AABlendSplitFn(torch.autograd.Function):
    """_AABlendFn on a colour given as two tensors, channels (n, C−1) and a last channel (n,) (render_cloth's
    rgb and coverage), returned the same way: no interleaved slicing or copies of one (n, C) image."""

    @staticmethod
    def forward(ctx, rgb, last, f, pf, po, target):
        ctx.set_materialize_grads(False)
        d_rgb = rgb.index_select(0, pf) - rgb.index_select(0, po)  # (K, C−1)
        d_last = last.index_select(0, pf) - last.index_select(0, po)  # (K,)
        rgb_out = rgb.clone().index_add_(0, target, d_rgb * f[:, None])
        last_out = last.clone().index_add_(0, target, d_last * f)
        ctx.save_for_backward(f, pf, po, target, d_rgb, d_last)
        return rgb_out, last_out

    @staticmethod
    def backward(ctx, g_rgb, g_last):
        f, pf, po, target, d_rgb, d_last = ctx.saved_tensors
        g_f = None
        outs = []
        for gg, d, need in ((g_rgb, d_rgb, ctx.needs_input_grad[0]), (g_last, d_last, ctx.needs_input_grad[1])):
            if gg is None:
                outs.append(None)
                continue
            g_t = gg.index_select(0, target)
            if ctx.needs_input_grad[2]:
                prod = g_t * d
                if prod.dim() == 2:
                    acc = prod[:, 0]
                    for c in range(1, prod.shape[1]):
                        acc = acc + prod[:, c]
                    prod = acc
                g_f = prod if g_f is None else g_f + prod
            if need:
                gd = g_t * (f[:, None] if g_t.dim() == 2 else f)
                outs.append(gg.clone().index_add_(0, pf, gd).index_add_(0, po, gd, alpha=-1))
            else:
                outs.append(None)
        return outs[0], outs[1], g_f, None, None, None


class _ScatterPlanar(torch.autograd.Function):
    """out = zeros(n, C); out[idx] = vals.T for planar vals (C, P) (idx unique); the backward gathers
    each channel into a contiguous row (no transposition of an interleaved gradient)."""

    @staticmethod
    def forward(ctx, vals, idx, n):
        out = vals.new_zeros(n, vals.shape[0]).index_copy_(0, idx, vals.T)
        ctx.save_for_backward(idx)
        return out

    @staticmethod
    def backward(ctx, g):
        (idx,) = ctx.saved_tensors
        gv = g.new_empty(g.shape[1], idx.shape[0])
        for c in range(g.shape[1]):
            torch.index_select(g[:, c], 0, idx, out=gv[c])
        return gv, None, None


class TorchRasterizer:
    """The PyTorch backend (any device). Stateless apart from the topology cache."""

    name = "torch"

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)

    rasterize = staticmethod(rasterize)
    interpolate = staticmethod(interpolate)
    texture = staticmethod(texture)
    antialias = staticmethod(antialias)

    def __repr__(self) -> str:
        return f"TorchRasterizer(device={self.device})"


# ------------------------------------------------------------------------------------------ compact kernels
# Used by render_cloth's torch path: everything on the covered pixels only, hand-written backwards.
class _InterpFn(torch.autograd.Function):
    """out (P, C) = Σ_k bw[k] · A[idx[k]] with A (N, C) vertex attributes, idx (3, P)."""

    @staticmethod
    def forward(ctx, bw, A, idx):
        a = A.index_select(0, idx.reshape(-1)).reshape(3, -1, A.shape[1])
        out = bw[0, :, None] * a[0] + bw[1, :, None] * a[1] + bw[2, :, None] * a[2]
        ctx.save_for_backward(bw, A, idx)
        return out

    @staticmethod
    def backward(ctx, g):
        bw, A, idx = ctx.saved_tensors
        g_bw = g_A = None
        if ctx.needs_input_grad[0]:
            a = A.index_select(0, idx.reshape(-1)).reshape(3, -1, A.shape[1])
            g_bw = (a * g).sum(-1)
        if ctx.needs_input_grad[1]:
            g_A = torch.zeros_like(A).index_add_(0, idx.reshape(-1), (bw[..., None] * g).reshape(-1, A.shape[1]))
        return g_bw, g_A, None


def interp_compact(bw: torch.Tensor, attr: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Interpolate per-vertex attributes attr (N, C) at the covered pixels: (P, C)."""
    return _InterpFn.apply(bw, attr, idx)


class _PyramidFn(torch.autograd.Function):
    """Box-filtered mip levels 1..n−1 of an NCHW texture (odd sizes drop the last row/column); the
    backward spreads each level's gradient back to level 0 with the adjoint of 2×2 averaging (an expand),
    much cheaper than autograd through avg_pool2d."""

    @staticmethod
    def forward(ctx, t0, n_levels):
        levels = [t0]
        for _ in range(n_levels - 1):
            t = levels[-1]
            N, C, h, w = t.shape
            h2, w2 = max(1, h // 2), max(1, w // 2)
            fy, fx = (2 if h >= 2 else 1), (2 if w >= 2 else 1)
            t = t[..., :h2 * fy, :w2 * fx].reshape(N, C, h2, fy, w2, fx).mean(dim=(3, 5))
            levels.append(t)
        ctx.shapes = [t.shape for t in levels]
        return tuple(levels[1:])

    @staticmethod
    def backward(ctx, *grads):
        shapes = ctx.shapes
        acc = None
        for lvl in range(len(shapes) - 1, 0, -1):
            g = grads[lvl - 1]
            if g is not None:
                acc = g if acc is None else acc + g
            if acc is None:
                continue
            N, C, h, w = shapes[lvl - 1]
            _, _, h2, w2 = acc.shape
            fy, fx = (2 if h >= 2 else 1), (2 if w >= 2 else 1)
            up = acc[:, :, :, None, :, None].expand(N, C, h2, fy, w2, fx).reshape(N, C, h2 * fy, w2 * fx)
            up = up * (1.0 / (fy * fx))
            if (h2 * fy, w2 * fx) != (h, w):
                up = F.pad(up, (0, w - w2 * fx, 0, h - h2 * fy))
            acc = up
        return acc, None


def _mip_count(h: int, w: int) -> int:
    n = 1
    while h > 1 or w > 1:
        h, w = max(1, h // 2), max(1, w // 2)
        n += 1
    return n


def texture_compact(tex: torch.Tensor, uv: torch.Tensor, uv_da: torch.Tensor | None = None,
                    boundary_mode: str = "clamp", max_mip_level: int | None = None) -> torch.Tensor:
    """Texture lookup for P pixels: tex (Ht, Wt, C), uv (P, 2) (nvdiffrast convention), uv_da (P, 4) or
    None (bilinear) → (P, C); trilinear over the box-filtered pyramid, one grid_sample per mip level on
    the pixels that use it. Differentiable w.r.t. tex and uv."""
    Ht, Wt, C = tex.shape
    P = uv.shape[0]
    t0 = tex.permute(2, 0, 1)[None].contiguous()
    if uv_da is None or P == 0:
        return _sample(t0, uv, boundary_mode)
    with torch.no_grad():
        lx2 = (uv_da[:, 0] * Wt) ** 2 + (uv_da[:, 2] * Ht) ** 2
        ly2 = (uv_da[:, 1] * Wt) ** 2 + (uv_da[:, 3] * Ht) ** 2
        lod = 0.5 * torch.log2(torch.maximum(lx2, ly2).clamp_min(1e-30))
        max_levels = _mip_count(Ht, Wt)
        if max_mip_level is not None:
            max_levels = min(max_levels, int(max_mip_level) + 1)
        lod = lod.clamp(0.0, max_levels - 1)
        lo_f = lod.floor()
        frac = (lod - lo_f).to(uv.dtype)
        lo = lo_f.long()
        lmin, lmax = int(lo.min()), int(lo.max())
        n_levels = min(max_levels, lmax + 2)
    levels = [t0] + (list(_PyramidFn.apply(t0, n_levels)) if n_levels > 1 else [])
    out = None
    for level in range(lmin, n_levels):
        with torch.no_grad():
            wgt = torch.where(lo == level, 1.0 - frac, torch.where(lo == level - 1, frac, torch.zeros_like(frac)))
            sel = torch.nonzero(wgt > 0).squeeze(1)
        if sel.numel() == 0:
            continue
        if sel.numel() == P:
            contrib = _sample(levels[level], uv, boundary_mode) * wgt[:, None]
            out = contrib if out is None else out + contrib
        else:
            contrib = _sample(levels[level], uv[sel], boundary_mode) * wgt[sel, None]
            if out is None:
                out = uv.new_zeros(P, C, dtype=tex.dtype)
            out = out.index_add(0, sel, contrib)
    return out if out is not None else uv.new_zeros(P, C, dtype=tex.dtype)


def antialias_core(color: torch.Tensor, tid_img: torch.Tensor, depth_img: torch.Tensor, pos: torch.Tensor,
                   tri: torch.Tensor, split: bool = False):
    """antialias() on a triangle-id image (B, H, W) long (−1 empty) and a depth image (inf empty).
    split=True: color is a pair (channels (B, H, W, C−1), last channel (B, H, W)) and so is the result
    (render_cloth's rgb and coverage; cheaper than slicing one interleaved image, also in the backward)."""
    return _antialias_impl(color, tid_img, depth_img, pos, tri, split=split)


# ------------------------------------------------------------------------------------------ plane kernels
# Used by render_cloth's torch path. In clip space the (unnormalised) perspective-correct barycentric of
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
    tf = tri.reshape(-1)
    p = pos.index_select(1, tf).reshape(B, T, 3, 4)  # index_select: its backward is an index_add
    x, y, z, w = p.unbind(-1)  # (B, T, 3)
    with torch.no_grad():
        sw = w.sum(-1)
        ok = sw.abs() > _W_EPS
        sw = torch.where(ok, sw, torch.ones_like(sw))
        rx = torch.where(ok, x.sum(-1) / sw, torch.zeros_like(sw))
        ry = torch.where(ok, y.sum(-1) / sw, torch.zeros_like(sw))
    X = x - rx[..., None] * w
    Y = y - ry[..., None] * w
    Xi, Yi, wi = X.roll(-1, -1), Y.roll(-1, -1), w.roll(-1, -1)
    Xj, Yj, wj = X.roll(-2, -1), Y.roll(-2, -1), w.roll(-2, -1)
    alpha = Xi * Yj - Xj * Yi  # (B, T, 3): c_k at (rx, ry)
    beta = wj * Yi - wi * Yj  # dc_k/dnx
    gamma = Xj * wi - Xi * wj  # dc_k/dny
    cm = torch.stack([alpha, beta, gamma], dim=-2)  # (B, T, 3 coef, 3 vertex)
    if uv.dim() == 2:
        uv = uv[None]
    attr = torch.cat([uv.expand(B, -1, -1), pos[..., 3:4], normals], dim=-1)
    attr = attr.index_select(1, tf).reshape(B, T, 3, 6)
    num = cm @ attr  # (B, T, 3, 6): u, v, w, n
    s = cm.sum(-1, keepdim=True)
    cz = (cm * z[:, :, None, :]).sum(-1, keepdim=True)
    tab = torch.cat([s, num, cm[..., 0:2], cz], dim=-1)  # (B, T, 3, 10) in PLANE_COLS order
    return torch.cat([rx.reshape(B * T, 1), ry.reshape(B * T, 1), tab.reshape(B * T, 3 * _NP)], dim=1)


class _PlaneFn(torch.autograd.Function):
    """Per-pixel evaluation of a plane_table, structure-of-arrays (one row per quantity, contiguous over
    pixels): uv (2, P), depth w (P,), normal (3, P) with gradient to the table, and without gradient
    bw (2, P), z/w (P,), uv_da (4, P) = (du/dX, du/dY, dv/dX, dv/dY) in pixels."""

    @staticmethod
    def forward(ctx, table, idx, nx, ny, H, W):
        ctx.set_materialize_grads(False)
        tt = table.T.contiguous()
        g = tt.new_empty(tt.shape[0], idx.shape[0])  # (32, P): one 1-D gather per row (much faster on CPU
        for r in range(tt.shape[0]):  # than index_select along dim 1 or a transpose of a row gather)
            torch.index_select(tt[r], 0, idx, out=g[r])
        dx = nx - g[0]
        dy = ny - g[1]
        a, b, c = g[2:2 + _NP], g[2 + _NP:2 + 2 * _NP], g[2 + 2 * _NP:]
        num = torch.addcmul(a, b, dx)
        num.addcmul_(c, dy)  # (10, P)
        s = num[0]
        inv_s = torch.where(s == 0, torch.ones_like(s), s).reciprocal_()
        vals = num[1:9] * inv_s  # u, v, w, n0, n1, n2, bw0, bw1
        uv, depth, nrm, bw = vals[0:2], vals[2], vals[3:6], vals[6:8]
        cw = num[3]
        zw = num[9] / torch.where(cw == 0, torch.ones_like(cw), cw)
        # screen derivatives of u and v: d(N/s) = (dN − (N/s) ds)/s, NDC → pixels: ×2/W, ×2/H
        sx, sy = inv_s * (2.0 / W), inv_s * (2.0 / H)
        uv_da = torch.empty(4, uv.shape[1], dtype=uv.dtype, device=uv.device)
        for r, (d, k, sc) in enumerate(((b, 1, sx), (c, 1, sy), (b, 2, sx), (c, 2, sy))):
            torch.mul(torch.addcmul(d[k], uv[k - 1], d[0], value=-1.0), sc, out=uv_da[r])
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


# ------------------------------------------------------------------------------------------ fast texture
def _down2(t: torch.Tensor) -> torch.Tensor:
    """2×2 box filter of a planar (C, h, w) level (odd sizes drop the last row/column), as _PyramidFn."""
    _, h, w = t.shape
    h2, w2 = max(1, h // 2), max(1, w // 2)
    fy, fx = (2 if h >= 2 else 1), (2 if w >= 2 else 1)
    t = t[:, :h2 * fy, :w2 * fx]
    if fy == 2:
        t = t[:, 0::2] + t[:, 1::2]
    if fx == 2:
        t = t[:, :, 0::2] + t[:, :, 1::2]
    return t * (1.0 / (fy * fx)) if fy * fx > 1 else t.clone()


def _down2_adjoint_add_(acc: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """acc += _down2_adjoint(g, acc.shape), in place with strided adds (no upsampled temporary)."""
    _, h, w = acc.shape
    _, h2, w2 = g.shape
    fy, fx = (2 if h >= 2 else 1), (2 if w >= 2 else 1)
    g = g * (1.0 / (fy * fx))
    for oy in range(fy):
        for ox in range(fx):
            acc[:, oy:h2 * fy:fy, ox:w2 * fx:fx] += g
    return acc


def _down2_hwc(t: torch.Tensor) -> torch.Tensor:
    """_down2 of an (h, w, C) level, (h/2, w/2, C) contiguous; even sizes without small-dimension
    strided operations (rows of 2C floats are contiguous in HWC memory)."""
    h, w, C = t.shape
    if h >= 2 and w >= 2 and h % 2 == 0 and w % 2 == 0 and t.is_contiguous():
        r = t.view(h // 2, 2, w // 2, 2 * C)
        r = r[:, 0] + r[:, 1]
        return (r[..., :C] + r[..., C:]) * 0.25
    return _down2(t.permute(2, 0, 1)).permute(1, 2, 0).contiguous()


def _down2_adjoint_add_hwc_(acc: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """acc (h, w, C) += adjoint of _down2_hwc applied to g (h/2, w/2, C), in place."""
    h, w, C = acc.shape
    if h >= 2 and w >= 2 and h % 2 == 0 and w % 2 == 0 and acc.is_contiguous():
        g2 = torch.cat([g, g], dim=-1).mul_(0.25)  # (h/2, w/2, 2C): both columns of a pair
        a = acc.view(h // 2, 2, w // 2, 2 * C)
        a[:, 0] += g2
        a[:, 1] += g2
        return acc
    _down2_adjoint_add_(acc.permute(2, 0, 1), g.permute(2, 0, 1))
    return acc


def _bilinear_taps(u: torch.Tensor, v: torch.Tensor, h: int, w: int):
    """Clamp-to-edge bilinear lookup at the texel-centre convention (grid_sample, border padding,
    align_corners=False): tap indices (4, P) into the h·w texels (order 00, 01, 10, 11), fractions fx, fy,
    and the masks where the coordinate is strictly inside (where grid_sample's coordinate gradient is 1)."""
    x = u * w - 0.5
    y = v * h - 0.5
    insx = (x > 0) & (x < w - 1)
    insy = (y > 0) & (y < h - 1)
    x = x.clamp(0.0, w - 1.0)
    y = y.clamp(0.0, h - 1.0)
    # the left/top tap at most at w−2 / h−2 (fx = 1 at the last texel): constant tap offsets
    x0f = x.floor().clamp_(max=max(w - 2, 0))
    y0f = y.floor().clamp_(max=max(h - 2, 0))
    fx = x - x0f
    fy = y - y0f
    i00 = (y0f * w + x0f).long()
    ox, oy = (1 if w >= 2 else 0), (w if h >= 2 else 0)
    offs = torch.tensor([0, ox, oy, oy + ox], device=u.device)
    return i00[None] + offs[:, None], fx, fy, insx, insy


class _TexFn(torch.autograd.Function):
    """Trilinear (or bilinear) clamp-mode texture lookup on a box-filtered pyramid, structure-of-arrays:
    taps and weights (4, P), output (C, P), every per-pixel operation on contiguous rows. Every level is
    read and its gradient written in the caller's (h, w, C) layout (a transposition of a 512² texture
    costs more than the lookups). Texel t, channel c of a level sits at t·a + c·b of its flat storage. Hand-written backward (an index_add per channel and level, the
    pyramid's adjoint, and the coordinate gradient)."""

    @staticmethod
    def forward(ctx, tex, u, v, lo, frac, n_levels):
        Ht, Wt, C = tex.shape
        P = u.shape[0]
        t0 = tex.detach().contiguous()
        levels = [t0.permute(2, 0, 1)]  # (C, h, w) views of HWC storage
        layout = [(t0.reshape(-1), C, 1)]
        for _ in range(n_levels - 1):
            t = _down2_hwc(levels[-1].permute(1, 2, 0))
            levels.append(t.permute(2, 0, 1))
            layout.append((t.reshape(-1), C, 1))
        if lo is None:  # every pixel on level 0 with weight 1
            plan = [(0, None, None)]
        else:
            lmin, lmax = int(lo.min()), int(lo.max())
            plan = []
            for level in range(lmin, min(n_levels, lmax + 2)):
                wgt = torch.where(lo == level, 1.0 - frac, torch.where((lo == level - 1) & (frac > 0), frac,
                                                                        torch.zeros_like(frac)))
                if lmin == lmax == level:
                    plan.append((level, None, wgt))
                    continue
                sel = torch.nonzero(wgt > 0).squeeze(1)
                if sel.numel():
                    plan.append((level, sel, wgt.index_select(0, sel)))
        out = None
        saved = []
        for level, sel, a in plan:
            t = levels[level]
            _, h, w = t.shape
            us, vs = (u, v) if sel is None else (u.index_select(0, sel), v.index_select(0, sel))
            idx, fx, fy, insx, insy = _bilinear_taps(us, vs, h, w)
            gx, gy = 1.0 - fx, 1.0 - fy
            bw = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy])  # (4, S)
            if a is not None:
                bw *= a
            bw = bw.to(t.dtype)
            flat, la, lb = layout[level]
            idx_a = idx * la if la != 1 else idx
            tv = bw.new_empty(C, 4, idx.shape[1])
            for c in range(C):
                torch.index_select(flat, 0, (idx_a + c * lb).reshape(-1), out=tv[c].view(-1))
            val = (tv * bw).sum(1)  # (C, S)
            if sel is None:
                out = val if out is None else out + val
            else:
                if out is None:
                    out = val.new_zeros(C, P)
                out.index_add_(1, sel, val)
            saved.append((level, sel, a, idx_a, fx, fy, insx, insy, bw, tv))
        ctx.saved = saved
        ctx.shapes = [t.shape for t in levels]
        ctx.layout = [(la, lb) for _, la, lb in layout]
        ctx.needs = ctx.needs_input_grad[:3]
        ctx.uv_dtype = u.dtype
        return out

    @staticmethod
    def backward(ctx, g):
        need_tex, need_u, need_v = ctx.needs
        shapes = ctx.shapes
        g = g.contiguous()  # (C, P)
        C = g.shape[0]
        g_lvl = [None] * len(shapes)
        gu = g.new_zeros(g.shape[1], dtype=ctx.uv_dtype) if need_u else None  # the texture's dtype may differ
        gv = g.new_zeros(g.shape[1], dtype=ctx.uv_dtype) if need_v else None
        def level_grad(level):  # zero gradient of a level as a (C, h, w) view of its storage layout
            _, h, w = shapes[level]
            buf = g.new_zeros(h * w * C)
            view = buf.view(h, w, C).permute(2, 0, 1) if ctx.layout[level][1] == 1 else buf.view(C, h, w)
            return buf, view

        bufs = {}
        for level, sel, a, idx_a, fx, fy, insx, insy, bw, tv in ctx.saved:
            _, h, w = shapes[level]
            gs = g if sel is None else g.index_select(1, sel)
            if need_tex:
                if g_lvl[level] is None:
                    bufs[level], g_lvl[level] = level_grad(level)
                buf = bufs[level]
                lb = ctx.layout[level][1]
                for c in range(C):
                    buf.index_add_(0, (idx_a + c * lb).reshape(-1), (bw * gs[c]).reshape(-1))
            if gu is not None or gv is not None:
                gd = tv[0] * gs[0]
                for c in range(1, C):
                    gd.addcmul_(tv[c], gs[c])  # (4, S): <g, texel k>
                gd = gd.to(fx.dtype)
                if a is not None:
                    gd *= a
                gx, gy = 1.0 - fx, 1.0 - fy
                if gu is not None:  # d/dx of the blend: (1−fy)(t01 − t00) + fy (t11 − t10)
                    d = (gy * (gd[1] - gd[0]) + fy * (gd[3] - gd[2])) * (w * insx.to(fx.dtype))
                    if sel is None:
                        gu += d
                    else:
                        gu.index_add_(0, sel, d)
                if gv is not None:
                    d = (gx * (gd[2] - gd[0]) + fx * (gd[3] - gd[1])) * (h * insy.to(fx.dtype))
                    if sel is None:
                        gv += d
                    else:
                        gv.index_add_(0, sel, d)
        g_tex = None
        if need_tex:
            for level in range(len(shapes) - 1, 0, -1):  # coarse to fine: add each level's adjoint
                if g_lvl[level] is None:
                    continue
                if g_lvl[level - 1] is None:
                    bufs[level - 1], g_lvl[level - 1] = level_grad(level - 1)
                _down2_adjoint_add_hwc_(g_lvl[level - 1].permute(1, 2, 0), g_lvl[level].permute(1, 2, 0))
            if g_lvl[0] is None:
                bufs[0], g_lvl[0] = level_grad(0)
            g_tex = bufs[0].view(shapes[0][1], shapes[0][2], C)
        return g_tex, gu, gv, None, None, None


def texture_fast(tex: torch.Tensor, u: torch.Tensor, v: torch.Tensor, uv_da: torch.Tensor | None = None,
                 max_mip_level: int | None = None) -> torch.Tensor:
    """texture_compact(tex, stack([u, v], 1), uv_da.T, 'clamp', max_mip_level).T for render_cloth, in
    value and gradient, structure-of-arrays: tex (Ht, Wt, C), u, v (P,), uv_da (4, P) or None → (C, P).
    Differentiable w.r.t. tex, u and v."""
    Ht, Wt, C = tex.shape
    if u.shape[0] == 0:
        return u.new_zeros(C, 0, dtype=tex.dtype)
    lo = frac = None
    n_levels = 1
    if uv_da is not None:
        with torch.no_grad():
            lx2 = (uv_da[0] * Wt).square_().add_((uv_da[2] * Ht).square_())
            ly2 = (uv_da[1] * Wt).square_().add_((uv_da[3] * Ht).square_())
            m2 = torch.maximum(lx2, ly2)
            max_levels = _mip_count(Ht, Wt)
            if max_mip_level is not None:
                max_levels = min(max_levels, int(max_mip_level) + 1)
            if max_levels > 1 and bool((m2 > 1.0).any()):  # else lod ≤ 0 everywhere: level 0 only
                lod = (0.5 * torch.log2(m2.clamp_min(1e-30))).clamp_(0.0, max_levels - 1)
                lo_f = lod.floor()
                frac = (lod - lo_f).to(u.dtype)
                lo = lo_f.long()
                n_levels = min(max_levels, int(lo.max()) + 2)
    return _TexFn.apply(tex, u, v, lo, frac, n_levels)
