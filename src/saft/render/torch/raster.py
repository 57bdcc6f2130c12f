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

Conventions follow nvdiffrast (see ``saft.render``): rast (B, H, W, 4) = (u, v, z/w, triangle_id + 1);
row r of the output is at y_ndc = (2r+1)/H − 1.
"""

from __future__ import annotations

import math

import torch

from saft.render.torch.rows import check_pos_tri, scatter_rows

_EDGE_EPS = 1e-4  # pixels: pixel centres this close outside a triangle still count as covered
W_EPS = 1e-9  # triangles with a vertex at w ≤ this (at or behind the eye) are discarded
_INT64_MAX = torch.iinfo(torch.int64).max


# ------------------------------------------------------------------------------------------ visibility
@torch.no_grad()
def visibility(pos: torch.Tensor, tri: torch.Tensor, resolution: tuple[int, int]):
    """Discrete part of rasterization: (pix, tid), the flat index b·H·W + row·W + col of every covered
    pixel (ascending) and the index of the triangle seen there. No autograd.

    Structure-of-arrays throughout (per-vertex / per-edge quantities are separate contiguous rows, the
    three-way minima and maxima explicit, gathers by index_select): small-dimension reductions and
    advanced indexing are several times slower on CPU."""
    pos, tri = check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B, V, _ = pos.shape
    T = tri.shape[0]
    dev = pos.device
    g = pos.detach().permute(2, 0, 1).index_select(2, tri.T.reshape(-1)).reshape(4, B, 3, T)
    w = g[3]  # (B, 3 vertices, T)
    okw = w > W_EPS
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


def pixel_ndc(pix: torch.Tensor, H: int, W: int, dtype):
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
    ndc_x, ndc_y = pixel_ndc(pix, H, W, pos.dtype)
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
    pos, tri = check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B = pos.shape[0]
    pix, tid = visibility(pos, tri, (H, W))
    res = barycentrics(pos, tri, pix, tid, (H, W), with_db=with_db)
    uvz, db = res if with_db else (res, None)
    vals = torch.cat([uvz, (tid + 1).to(pos.dtype)[:, None]], dim=-1)
    rast = scatter_rows(vals, pix, B * H * W).reshape(B, H, W, 4)
    if not with_db:
        return rast
    rast_db = torch.zeros(B * H * W, 4, dtype=pos.dtype, device=pos.device)
    rast_db[pix] = db
    return rast, rast_db.reshape(B, H, W, 4)

