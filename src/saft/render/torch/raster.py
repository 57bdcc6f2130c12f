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
import threading

import torch

from saft.render.topology import topology
from saft.render.torch import raster_numba
from saft.render.torch.rows import check_pos_tri, const, scatter_rows

_EDGE_EPS = 1e-4  # pixels: pixel centres this close outside a triangle still count as covered
W_EPS = 1e-9  # triangles with a vertex at w ≤ this (at or behind the eye) are discarded
_INT64_MAX = torch.iinfo(torch.int64).max
_ZBUF = threading.local()  # raster_numba's z-buffer per thread (outputs render on a pool), cleared after each use
USE_NUMBA = True  # CPU tensors take raster_numba's scanline loop (tests switch it off to check the torch path)


# ------------------------------------------------------------------------------------------ visibility
@torch.no_grad()
def visibility(pos: torch.Tensor, tri: torch.Tensor, resolution: tuple[int, int]):
    """Discrete part of rasterization: (pix, tid), the flat index b·H·W + row·W + col of every covered
    pixel (ascending) and the index of the triangle seen there. No autograd.

    Few ops, whatever the mesh or image size (each op is a kernel launch on a GPU): per-triangle
    quantities are computed stacked ((x, y) together, the three vertices or edges together), the
    expansions triangle → rows → pixels are one repeat_interleave of a per-triangle (per-row) table each,
    whose zero counts drop the empty entries without a compaction. Three host syncs: the two expansion
    sizes and the final nonzero."""
    pos, tri = check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B = pos.shape[0]
    T = tri.shape[0]
    dev = pos.device
    g = pos.detach().permute(2, 0, 1).index_select(2, topology(tri).tri_flat_t).reshape(4, B, 3, T)
    okw = g[3] > W_EPS
    ok = okw.all(1)  # (B, T)
    p = g[:3] / torch.where(okw, g[3], 1.0)  # x/w, y/w, z/w: (3, B, 3 vertices, T)
    xy = (p[:2] + 1.0) * const((0.5 * W, 0.5 * H), p).view(2, 1, 1, 1) - 0.5  # pixels, column j at x = j
    z = p[2]
    # edge function k (opposite vertex k, from vertex k+1 to k+2): e_k = A x + B y + C, e_k(vertex k) = 2·area
    xyi, xyj = xy.roll(-1, 2), xy.roll(-2, 2)
    A = xyi[1] - xyj[1]
    Bc = xyj[0] - xyi[0]
    C = -(A * xyi[0] + Bc * xyi[1])
    area2 = A[:, 0] * xy[0, :, 0] + Bc[:, 0] * xy[1, :, 0] + C[:, 0]
    a2 = area2.abs()
    ok &= (a2 > 1e-12) & (z.amin(1) <= 1) & (z.amax(1) >= -1)  # degenerate or wholly beyond near or far
    ABC = torch.stack([A, Bc, C]) * area2.sign()[None, :, None]  # (3, B, 3, T), inside ≥ 0 (area 0: culled)
    zm = ABC * z
    zABC = (zm[:, :, 0] + zm[:, :, 1] + zm[:, :, 2]) / a2.clamp_min(1e-30)  # z/w is affine in screen space
    lo = torch.ceil(xy.amin(2) - _EDGE_EPS).clamp_min(0)  # (x|y, B, T) pixel bounding box
    hi = torch.minimum(torch.floor(xy.amax(2) + _EDGE_EPS), const((W - 1, H - 1), p).view(2, 1, 1))
    drawn = ok & (hi >= lo).all(0)  # (B, T): kept and with a pixel centre in its bounding box
    if USE_NUMBA and dev.type == "cpu":
        return _visibility_numba(ABC, zABC, lo[1], torch.where(drawn, hi[1], lo[1] - 1), B, H, W)
    nrows = torch.where(drawn, hi[1] - lo[1] + 1, 0.0).long().reshape(-1)  # (B·T,)
    R = int(nrows.sum())
    if R == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    start = torch.cumsum(nrows, 0) - nrows
    # per triangle: A, B, C of the three edges (9), zA, zB, zC, first row − its start in the row list,
    # and b·T + t (exact in floating point below 2**24); one row of the list per covered pixel row
    inst = torch.arange(B * T, device=dev, dtype=p.dtype)
    tab = torch.cat([ABC.permute(0, 2, 1, 3).reshape(9, B * T), zABC.reshape(3, B * T),
                     (lo[1].reshape(-1) - start.to(p.dtype))[None], inst[None]])
    tab = torch.repeat_interleave(tab, nrows, dim=1, output_size=R)  # (14, R)
    row = tab[12] + torch.arange(R, device=dev, dtype=p.dtype)
    Ai, Bi, Ci = tab[0:3], tab[3:6], tab[6:9]
    num = -(Bi * row + Ci)  # inside ⇔ A x ≥ num for all three edges
    a0 = Ai == 0
    bound = num / Ai.masked_fill(a0, 1.0)
    xl = torch.ceil(bound.masked_fill(Ai <= 0, -math.inf).amax(0) - _EDGE_EPS).clamp_min(0)
    xr = torch.floor(bound.masked_fill(Ai >= 0, math.inf).amin(0) + _EDGE_EPS).clamp_max(W - 1)
    flat_bad = (a0 & (num > _EDGE_EPS * Bi.abs())).any(0)
    span = (xr - xl + 1).clamp_min(0).masked_fill(flat_bad, 0.0).long()
    N = int(span.sum())
    if N == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    pstart = torch.cumsum(span, 0) - span
    inst_r = tab[13].long()
    b = torch.div(inst_r, T, rounding_mode="floor") if B > 1 else torch.zeros_like(inst_r)
    # per row: the column of its first candidate minus that candidate's place in the list, the flat index
    # of the row's first pixel, the triangle; z/w along the row (zB row + zC) and its slope zA. Gathered per
    # candidate by 1-D index_selects: contiguous results (a repeat_interleave of a row table gives strided
    # columns, which made this part 10 % slower on CPU at 700x800, for 3 ops fewer)
    pair = torch.repeat_interleave(span, output_size=N)
    px = torch.arange(N, device=dev) + (xl.long() - pstart).index_select(0, pair)
    pix = ((b * H + row.long()) * W).index_select(0, pair) + px
    zpix = (tab[10] * row + tab[11]).index_select(0, pair) + tab[9].index_select(0, pair) * px.to(p.dtype)
    tid = (inst_r - b * T).index_select(0, pair)
    q = ((zpix.clamp(-1.0, 1.0) + 1.0) * float(2 ** 29)).long()  # 31 bits of depth
    key = torch.where((zpix >= -1.0) & (zpix <= 1.0), (q << 32) | tid, _INT64_MAX)
    zbuf = torch.full((B * H * W,), _INT64_MAX, dtype=torch.int64, device=dev)
    zbuf.scatter_reduce_(0, pix, key, reduce="amin", include_self=True)
    pix_out = torch.nonzero(zbuf != _INT64_MAX).squeeze(1)
    tid_out = zbuf.index_select(0, pix_out) & 0xFFFFFFFF
    return pix_out, tid_out


def _visibility_numba(ABC, zABC, row_lo, row_hi, B: int, H: int, W: int):
    """visibility's spans and depth test by raster_numba (CPU tensors), in a z-buffer kept between calls of
    the same size (collect leaves it cleared; a fresh one per call cost as much as the depth test)."""
    raster_numba.load()
    T = ABC.shape[-1]
    tab = torch.cat([ABC.permute(0, 2, 1, 3).reshape(9, B * T), zABC.reshape(3, B * T)]).double().contiguous()
    zbuf = getattr(_ZBUF, "buffer", None)
    if zbuf is None or zbuf.numel() != B * H * W:
        zbuf = _ZBUF.buffer = torch.full((B * H * W,), _INT64_MAX, dtype=torch.int64)
    rows_used = torch.tensor([[H, -1]] * B, dtype=torch.int64)
    raster_numba.depth_test(tab.numpy(), row_lo.long().reshape(-1).contiguous().numpy(),
                            row_hi.long().reshape(-1).contiguous().numpy(), T, H, W, _EDGE_EPS, zbuf.numpy(),
                            rows_used.numpy())
    size = int((rows_used[:, 1] - rows_used[:, 0] + 1).clamp_min(0).sum()) * W
    pix, tid = torch.empty(size, dtype=torch.int64), torch.empty(size, dtype=torch.int64)
    n = raster_numba.collect(zbuf.numpy(), rows_used.numpy(), H, W, pix.numpy(), tid.numpy())
    return pix[:n], tid[:n]


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

