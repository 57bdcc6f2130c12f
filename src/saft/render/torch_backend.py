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
    pixel (ascending) and the index of the triangle seen there. No autograd."""
    pos, tri = _check_pos_tri(pos, tri)
    H, W = int(resolution[0]), int(resolution[1])
    B, V, _ = pos.shape
    T = tri.shape[0]
    dev = pos.device
    p = pos.detach()[:, tri]  # (B, T, 3, 4)
    w = p[..., 3]
    ok = (w > _W_EPS).all(-1)
    w = torch.where(w > _W_EPS, w, torch.ones_like(w))
    x = (p[..., 0] / w + 1.0) * (0.5 * W) - 0.5  # pixel units, centre of column j at x = j
    y = (p[..., 1] / w + 1.0) * (0.5 * H) - 0.5
    z = p[..., 2] / w
    # edge function k (opposite vertex k, from vertex k+1 to k+2): e_k = A x + B y + C, e_k(vertex k) = 2·area
    xi, yi = x.roll(-1, -1), y.roll(-1, -1)
    xj, yj = x.roll(-2, -1), y.roll(-2, -1)
    A = yi - yj
    Bc = xj - xi
    C = -(A * xi + Bc * yi)
    area2 = A[..., 0] * x[..., 0] + Bc[..., 0] * y[..., 0] + C[..., 0]
    ok &= area2.abs() > 1e-12
    ok &= ~((z < -1).all(-1) | (z > 1).all(-1))
    s = torch.where(area2 < 0, -1.0, 1.0).to(x.dtype)
    A, Bc, C = A * s[..., None], Bc * s[..., None], C * s[..., None]
    inv_area = 1.0 / area2.abs().clamp_min(1e-30)
    zA = (A * z).sum(-1) * inv_area  # z/w is affine in screen space
    zB = (Bc * z).sum(-1) * inv_area
    zC = (C * z).sum(-1) * inv_area
    ymin = torch.ceil(y.amin(-1) - _EDGE_EPS).clamp(min=0)
    ymax = torch.floor(y.amax(-1) + _EDGE_EPS).clamp(max=H - 1)
    xmin = torch.ceil(x.amin(-1) - _EDGE_EPS).clamp(min=0)
    xmax = torch.floor(x.amax(-1) + _EDGE_EPS).clamp(max=W - 1)
    nrows = (ymax - ymin + 1).clamp(min=0)
    nrows = torch.where(ok & (xmax >= xmin), nrows, torch.zeros_like(nrows)).long().reshape(-1)

    inst = torch.nonzero(nrows > 0).squeeze(1)  # over B·T
    if inst.numel() == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    cnt = nrows[inst]
    R = int(cnt.sum())
    pair_inst = torch.repeat_interleave(inst, cnt, output_size=R)
    start = torch.cumsum(cnt, 0) - cnt
    row = ymin.reshape(-1)[pair_inst] + (
        torch.arange(R, device=dev) - torch.repeat_interleave(start, cnt, output_size=R)).to(x.dtype)
    Ai, Bi, Ci = A.reshape(-1, 3)[pair_inst], Bc.reshape(-1, 3)[pair_inst], C.reshape(-1, 3)[pair_inst]
    num = -(Bi * row[:, None] + Ci)  # inside ⇔ A x ≥ num for all three edges
    safeA = torch.where(Ai == 0, torch.ones_like(Ai), Ai)
    bound = num / safeA
    inf = torch.full_like(bound, math.inf)
    lo = torch.where(Ai > 0, bound, -inf).amax(-1)
    hi = torch.where(Ai < 0, bound, inf).amin(-1)
    flat_bad = ((Ai == 0) & (num > _EDGE_EPS * Bi.abs())).any(-1)
    xl = torch.ceil(lo - _EDGE_EPS).clamp(min=0)
    xr = torch.floor(hi + _EDGE_EPS).clamp(max=W - 1)
    span = (xr - xl + 1).clamp(min=0)
    span = torch.where(flat_bad, torch.zeros_like(span), span).long()
    keep = torch.nonzero(span > 0).squeeze(1)
    span, xl, row, pair_inst = span[keep], xl[keep], row[keep], pair_inst[keep]
    N = int(span.sum())
    if N == 0:
        e = torch.zeros(0, dtype=torch.int64, device=dev)
        return e, e
    pair = torch.repeat_interleave(torch.arange(span.numel(), device=dev), span, output_size=N)
    pstart = torch.cumsum(span, 0) - span
    local = torch.arange(N, device=dev) - pstart[pair]
    inst_p = pair_inst[pair]
    px = xl.long()[pair] + local
    zrow = zB.reshape(-1)[pair_inst] * row + zC.reshape(-1)[pair_inst]
    zpix = zrow[pair] + zA.reshape(-1)[inst_p] * px.to(x.dtype)
    b = inst_p // T
    tid = inst_p - b * T
    pix = (b * H + row.long()[pair]) * W + px
    inside = (zpix >= -1.0) & (zpix <= 1.0)
    q = ((zpix.clamp(-1.0, 1.0) + 1.0) * float(2 ** 29)).long()  # 31 bits of depth
    key = (q << 32) | tid
    if not bool(inside.all()):
        key = torch.where(inside, key, torch.full_like(key, _INT64_MAX))
    zbuf = torch.full((B * H * W,), _INT64_MAX, dtype=torch.int64, device=dev)
    zbuf.scatter_reduce_(0, pix, key, reduce="amin", include_self=True)
    pix_out = torch.nonzero(zbuf != _INT64_MAX).squeeze(1)
    tid_out = zbuf[pix_out] & 0xFFFFFFFF
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
    H, W = int(resolution[0]), int(resolution[1])
    B, V, _ = pos.shape
    b = torch.div(pix, H * W, rounding_mode="floor")
    ndc_x, ndc_y = _pixel_ndc(pix, H, W, pos.dtype)
    vid = tri[tid] + (b * V)[:, None]  # (P, 3)
    P3 = pos.reshape(-1, 4)[vid]  # (P, 3, 4)
    out, db = _BaryFn.apply(P3, ndc_x, ndc_y, with_db, H, W)
    return (out, db) if with_db else out


def _bary_forward(P3, ndc_x, ndc_y):
    X = P3[..., 0] - ndc_x[:, None] * P3[..., 3]
    Y = P3[..., 1] - ndc_y[:, None] * P3[..., 3]
    X1, X2 = X.roll(-1, -1), X.roll(-2, -1)
    Y1, Y2 = Y.roll(-1, -1), Y.roll(-2, -1)
    c = X1 * Y2 - X2 * Y1  # ∝ barycentric weight of each vertex
    return X, Y, c


class _BaryFn(torch.autograd.Function):
    """(u, v, z/w) from the three clip-space vertices of each pixel's triangle, with a hand-written
    backward (the autograd graph of the same expression is ~3× slower on CPU)."""

    @staticmethod
    def forward(ctx, P3, ndc_x, ndc_y, with_db, H, W):
        X, Y, c = _bary_forward(P3, ndc_x, ndc_y)
        s = c.sum(-1)
        inv_s = 1.0 / torch.where(s == 0, torch.ones_like(s), s)
        z, w = P3[..., 2], P3[..., 3]
        cz = (c * z).sum(-1)
        cw = (c * w).sum(-1)
        inv_cw = 1.0 / torch.where(cw == 0, torch.ones_like(cw), cw)
        out = torch.stack([c[:, 0] * inv_s, c[:, 1] * inv_s, cz * inv_cw], dim=-1)
        db = None
        if with_db:
            w1, w2 = w.roll(-1, -1), w.roll(-2, -1)
            X1, X2 = X.roll(-1, -1), X.roll(-2, -1)
            Y1, Y2 = Y.roll(-1, -1), Y.roll(-2, -1)
            dcx = -(w1 * Y2 - w2 * Y1)
            dcy = -(X1 * w2 - X2 * w1)
            dsx, dsy = dcx.sum(-1), dcy.sum(-1)
            b = c[:, :2] * inv_s[:, None]
            dbx = (dcx[:, :2] - b * dsx[:, None]) * inv_s[:, None] * (2.0 / W)
            dby = (dcy[:, :2] - b * dsy[:, None]) * inv_s[:, None] * (2.0 / H)
            db = torch.stack([dbx[:, 0], dby[:, 0], dbx[:, 1], dby[:, 1]], dim=-1)
        ctx.save_for_backward(P3, ndc_x, ndc_y)
        ctx.mark_non_differentiable(*([db] if db is not None else []))
        return out, db

    @staticmethod
    def backward(ctx, g_out, g_db):
        P3, ndc_x, ndc_y = ctx.saved_tensors
        X, Y, c = _bary_forward(P3, ndc_x, ndc_y)
        s = c.sum(-1)
        inv_s = 1.0 / torch.where(s == 0, torch.ones_like(s), s)
        z, w = P3[..., 2], P3[..., 3]
        cz = (c * z).sum(-1)
        cw = (c * w).sum(-1)
        inv_cw = 1.0 / torch.where(cw == 0, torch.ones_like(cw), cw)
        gu, gv, gz = g_out[:, 0], g_out[:, 1], g_out[:, 2]
        # u = c0/s, v = c1/s, q = cz/cw
        u, v, q = c[:, 0] * inv_s, c[:, 1] * inv_s, cz * inv_cw
        gs = -(gu * u + gv * v) * inv_s
        gc = gs[:, None].expand(-1, 3).clone()
        gc[:, 0] += gu * inv_s
        gc[:, 1] += gv * inv_s
        gcz = gz * inv_cw
        gcw = -gz * q * inv_cw
        gc = gc + gcz[:, None] * z + gcw[:, None] * w
        g_zv = gcz[:, None] * c  # direct dependence on z_i
        g_wv = gcw[:, None] * c
        # c_k = X_{k+1} Y_{k+2} − X_{k+2} Y_{k+1}
        X1, X2 = X.roll(-1, -1), X.roll(-2, -1)
        Y1, Y2 = Y.roll(-1, -1), Y.roll(-2, -1)
        # dc_k/dX_{k+1} = Y_{k+2}; dc_k/dX_{k+2} = −Y_{k+1}
        gX = (gc * Y2).roll(1, -1) - (gc * Y1).roll(2, -1)
        gY = -(gc * X2).roll(1, -1) + (gc * X1).roll(2, -1)
        gP = torch.stack([gX, gY, g_zv, g_wv - gX * ndc_x[:, None] - gY * ndc_y[:, None]], dim=-1)
        return gP, None, None, None, None, None


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
        out = vals.new_zeros(n, vals.shape[1])
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
    sel_all = None
    if mask is not None:
        sel_all = torch.nonzero(mask.reshape(-1)).squeeze(1)
        uvf = uvf[sel_all]
    t0 = tex.permute(0, 3, 1, 2)
    if filter_mode == "nearest":
        Ht, Wt = t0.shape[-2:]
        col = (uvf[:, 0] * Wt).floor().long().clamp(0, Wt - 1)
        row = (uvf[:, 1] * Ht).floor().long().clamp(0, Ht - 1)
        vals = tex[0][row, col]
    elif filter_mode == "linear":
        vals = _sample(t0, uvf, boundary_mode)
    else:
        Ht, Wt = t0.shape[-2:]
        with torch.no_grad():
            da = uv_da.reshape(-1, 4)
            if sel_all is not None:
                da = da[sel_all]
            lx2 = (da[:, 0] * Wt) ** 2 + (da[:, 2] * Ht) ** 2
            ly2 = (da[:, 1] * Wt) ** 2 + (da[:, 3] * Ht) ** 2
            lod = 0.5 * torch.log2(torch.maximum(lx2, ly2).clamp_min(1e-30))
        levels = mip_pyramid(t0, max_mip_level)
        lod = lod.clamp(0.0, len(levels) - 1)
        lo = lod.floor()
        frac = lod - lo
        lo = lo.long()
        vals = None
        lmin, lmax = int(lo.min()) if lo.numel() else 0, int(lo.max()) if lo.numel() else 0
        for level in range(lmin, min(lmax + 1, len(levels) - 1) + 1):
            with torch.no_grad():
                wgt = torch.where(lo == level, 1.0 - frac, torch.where(lo == level - 1, frac, 0.0))
                sel = torch.nonzero(wgt > 0).squeeze(1)
            if sel.numel() == 0:
                continue
            if sel.numel() == wgt.numel():
                contrib = _sample(levels[level], uvf, boundary_mode) * wgt[:, None].to(tex.dtype)
                vals = contrib if vals is None else vals + contrib
            else:
                contrib = _sample(levels[level], uvf[sel], boundary_mode) * wgt[sel, None].to(tex.dtype)
                if vals is None:
                    vals = uvf.new_zeros(uvf.shape[0], C).to(tex.dtype)
                vals = vals.index_add(0, sel, contrib)
        if vals is None:
            vals = uvf.new_zeros(uvf.shape[0], C).to(tex.dtype)
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
    pos, tri = _check_pos_tri(pos, tri)
    B, H, W, C = color.shape
    V = pos.shape[1]
    with torch.no_grad():
        sil = silhouette_edges(pos, tri, H, W)  # (B, T, 3)
        x, y = _screen_xy(pos.detach(), H, W)  # (B, V)
        tidf = rast.detach()[..., 3]
        depth = torch.where(tidf > 0, rast.detach()[..., 2], torch.full_like(tidf, math.inf))
        tid = tidf.long() - 1
        pairs = []
        for axis in (0, 1):  # 0: horizontal neighbours (j, j+1), 1: vertical (i, i+1)
            if axis == 0:
                diff = tid[:, :, :-1] != tid[:, :, 1:]
                a_idx = torch.nonzero(diff.reshape(-1)).squeeze(1)
                bb = torch.div(a_idx, H * (W - 1), rounding_mode="floor")
                rem = a_idx - bb * H * (W - 1)
                ii = torch.div(rem, W - 1, rounding_mode="floor")
                jj = rem - ii * (W - 1)
                pa = (bb * H + ii) * W + jj
                pb = pa + 1
            else:
                diff = tid[:, :-1, :] != tid[:, 1:, :]
                a_idx = torch.nonzero(diff.reshape(-1)).squeeze(1)
                bb = torch.div(a_idx, (H - 1) * W, rounding_mode="floor")
                rem = a_idx - bb * (H - 1) * W
                ii = torch.div(rem, W, rounding_mode="floor")
                jj = rem - ii * W
                pa = (bb * H + ii) * W + jj
                pb = pa + W
            dflat = depth.reshape(-1)
            a_front = dflat[pa] <= dflat[pb]
            pf = torch.where(a_front, pa, pb)  # the nearer pixel
            po = torch.where(a_front, pb, pa)
            t_f = tid.reshape(-1)[pf]
            bf = torch.div(pf, H * W, rounding_mode="floor")
            v0 = tri[t_f]  # (N, 3)
            v1 = v0.roll(-1, -1)
            gv0 = v0 + (bf * V)[:, None]
            gv1 = v1 + (bf * V)[:, None]
            xf, yf = x.reshape(-1), y.reshape(-1)
            x0, y0, x1, y1 = xf[gv0], yf[gv0], xf[gv1], yf[gv1]  # (N, 3) edge end points
            rem_f = pf - bf * H * W
            fi = torch.div(rem_f, W, rounding_mode="floor").to(x.dtype)
            fj = (rem_f % W).to(x.dtype)
            dx, dy = x1 - x0, y1 - y0
            if axis == 0:  # crossing of row fi, major axis vertical
                major = (dy.abs() >= dx.abs()) & (dy != 0)
                tpar = (fi[:, None] - y0) / torch.where(dy == 0, torch.ones_like(dy), dy)
                cross = x0 + tpar * dx
                sgn = torch.where(po > pf, 1.0, -1.0).to(x.dtype)
                tt = (cross - fj[:, None]) * sgn[:, None]
            else:
                major = dx.abs() > dy.abs()
                tpar = (fj[:, None] - x0) / torch.where(dx == 0, torch.ones_like(dx), dx)
                cross = y0 + tpar * dy
                sgn = torch.where(po > pf, 1.0, -1.0).to(x.dtype)
                tt = (cross - fi[:, None]) * sgn[:, None]
            ok = sil[bf[:, None], t_f[:, None], torch.arange(3, device=x.device)[None]] & major
            ok &= (tpar >= 0) & (tpar <= 1) & (tt >= 0) & (tt <= 1)
            has = ok.any(-1)
            k = torch.argmax(ok.to(torch.uint8), dim=-1)
            sel = torch.nonzero(has).squeeze(1)
            if sel.numel():
                ks = k[sel]
                pairs.append((axis, pf[sel], po[sel], gv0[sel, ks], gv1[sel, ks], fi[sel], fj[sel], sgn[sel]))
    out = color.reshape(-1, C)
    if not pairs:
        return color
    posf = pos.reshape(-1, 4)
    targets, deltas = [], []
    for axis, pf, po, e0, e1, fi, fj, sgn in pairs:
        xe0, ye0 = _screen_xy(posf[e0], H, W)
        xe1, ye1 = _screen_xy(posf[e1], H, W)
        if axis == 0:
            cross = xe0 + (fi - ye0) / (ye1 - ye0) * (xe1 - xe0)
            tt = (cross - fj) * sgn
        else:
            cross = ye0 + (fj - xe0) / (xe1 - xe0) * (ye1 - ye0)
            tt = (cross - fi) * sgn
        f = tt - 0.5  # > 0: the front triangle reaches into the other pixel; < 0: it leaves part of its own
        cf, co = out[pf], out[po]
        targets.append(torch.where(f.detach() > 0, po, pf))
        deltas.append(f[:, None].to(color.dtype) * (cf - co))
    return out.index_add(0, torch.cat(targets), torch.cat(deltas)).reshape(B, H, W, C)


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
