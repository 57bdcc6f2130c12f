"""antialias: nvdiffrast's analytic scheme — for each pair of horizontally or vertically adjacent pixels
with different triangles, a silhouette edge (mesh boundary, or an edge between a front- and a back-facing
triangle: folds) of the nearer triangle that crosses the segment between the two centres blends the
colours in proportion to where it crosses; the blend weight depends on the edge's projected end points,
which gives the silhouette gradients with respect to the positions.
"""

from __future__ import annotations

import math

import torch

from saft.render.topology import topology
from saft.render.torch.raster import W_EPS
from saft.render.torch.rows import check_pos_tri, const


def screen_xy(pos: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(B·V, 2) pixel coordinates (x = column, y = row; the centre of pixel (0, 0) at (0, 0)) of every
    vertex of pos (B, V, 4); differentiable."""
    p = pos.reshape(-1, 4)
    w = p[:, 3:4]
    w = w.masked_fill(w.abs() < W_EPS, W_EPS)
    return (p[:, :2] / w + 1.0) * const((0.5 * W, 0.5 * H), p) - 0.5


def _silhouette(xy: torch.Tensor, topo, B: int) -> torch.Tensor:
    """(B, T, 3) bool silhouette edges (see silhouette_edges) from the screen positions xy (B·V, 2)."""
    g = xy.view(B, -1, 2).index_select(1, topo.tri.reshape(-1)).view(B, -1, 3, 2)
    d = g[:, :, 1:] - g[:, :, :1]  # (B, T, 2 edges from vertex 0, x|y)
    front = d[..., 0, 0] * d[..., 1, 1] - d[..., 1, 0] * d[..., 0, 1] > 0  # twice the signed screen area
    return topo.boundary | (front[:, topo.nb] != front[..., None])


def silhouette_edges(pos: torch.Tensor, tri: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """(B, T, 3) bool: edge k of triangle t (tri[t, k] → tri[t, (k+1)%3]) is a silhouette edge in image b:
    on the mesh boundary, or shared with a triangle facing the other way in screen space (a fold)."""
    with torch.no_grad():
        pos, tri = check_pos_tri(pos, tri)
        return _silhouette(screen_xy(pos.detach(), H, W), topology(tri), pos.shape[0])


def antialias(color: torch.Tensor, rast: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """nvdiffrast-style analytic antialiasing of color (B, H, W, C); differentiable w.r.t. color and, through
    the blend weights, pos (silhouette gradients on boundary and fold edges)."""
    with torch.no_grad():
        tidf = rast.detach()[..., 3]
        tid_img = tidf.long() - 1
        depth_img = torch.where(tidf > 0, rast.detach()[..., 2], torch.full_like(tidf, math.inf))
    return antialias_core(color, tid_img, depth_img, pos, tri)


def antialias_core(color, tid_img, depth_img, pos, tri, split=False):
    """Both neighbour directions and the three edges of a triangle at once (the pairs of the two axes
    in one list, per-edge quantities as (3, K) rows), so that the op count does not grow with them: two
    host syncs (the nonzero of the pairs and of those whose front triangle has a silhouette edge); the
    pairs with no crossing edge blend with weight 0 instead of being compacted away."""
    pos, tri = check_pos_tri(pos, tri)
    if split:  # color = (channels (B, H, W, C−1), last channel (B, H, W)) as separate tensors
        B, H, W, C = color[0].shape[:3] + (color[0].shape[3] + 1,)
    else:
        B, H, W, C = color.shape
    V = pos.shape[1]
    T = tri.shape[0]
    n = B * H * W
    topo = topology(tri)
    xy = screen_xy(pos, H, W)  # (B·V, 2), differentiable: the blend weights below use it
    with torch.no_grad():
        sil = _silhouette(xy.detach(), topo, B).reshape(-1, 3)  # (B·T, 3)
        t = tid_img.reshape(B, H, W)
        # pairs (p, p+1) (axis 0) and (p, p+W) (axis 1) whose triangles differ, indexed axis·n + p
        diff = torch.zeros(2, B, H, W, dtype=torch.bool, device=t.device)
        torch.ne(t[:, :, :-1], t[:, :, 1:], out=diff[0, :, :, :-1])
        torch.ne(t[:, :-1], t[:, 1:], out=diff[1, :, :-1])
        idx = torch.nonzero(diff.view(-1)).squeeze(1)
        axis = torch.div(idx, n, rounding_mode="floor")
        pa = idx - axis * n
        pb = pa + (axis * (W - 1) + 1)
        dflat = depth_img.reshape(-1)
        a_front = dflat.index_select(0, pa) <= dflat.index_select(0, pb)
        pf = torch.where(a_front, pa, pb)  # the nearer pixel
        po = torch.where(a_front, pb, pa)
        bt = tid_img.reshape(-1).index_select(0, pf)
        if B > 1:
            bt = bt + torch.div(pf, H * W, rounding_mode="floor") * T
        keep = torch.nonzero(sil.any(1).index_select(0, bt)).squeeze(1)  # triangles with a silhouette edge
        if keep.numel() == 0:
            return color
        pf, po, bt, axis = torch.stack([pf, po, bt, axis]).index_select(1, keep)
        K = pf.shape[0]
        vk = topo.batched_triT(B, V).index_select(1, bt)  # (3, K) rows of xy of the front triangle's corners
        # per pair the coordinate along it (P: x for axis 0, y for axis 1) and across it (Q): xy.view(-1)
        # holds x of vertex v at 2v, y at 2v + 1
        pq = torch.stack([axis, 1 - axis])[:, None]  # (2, 1, K)
        PQ = xy.detach().view(-1).index_select(0, (2 * vk + pq).view(-1)).view(2, 3, K)
        dP, dQ = (PQ.roll(-1, 1) - PQ).unbind(0)  # (3, K): edge k from vertex k to k+1
        aP, aQ = dP.abs(), dQ.abs()
        # axis 0 crosses row fi with edges at least as vertical as horizontal (not flat), axis 1 column
        # fj with edges strictly more horizontal than vertical
        major = (aQ > aP) | ((aQ == aP) & (aQ > 0) & (axis == 0))
        rem = pf if B == 1 else pf - torch.div(pf, H * W, rounding_mode="floor") * (H * W)
        fi = torch.div(rem, W, rounding_mode="floor")
        fj = rem - fi * W
        fq = torch.where(axis == 0, fi, fj).to(xy.dtype)  # the line crossed: row or column
        fp = torch.where(axis == 0, fj, fi).to(xy.dtype)  # the pixel's coordinate along the pair
        sgn = (po > pf).to(xy.dtype) * 2.0 - 1.0
        tpar = (fq - PQ[1]) / dQ.masked_fill(dQ == 0, 1.0)
        tt = (PQ[0] + tpar * dP - fp) * sgn
        ok = sil.index_select(0, bt).T & major & (tpar >= 0) & (tpar <= 1) & (tt >= 0) & (tt <= 1)
        has = ok.any(0)
        no = ~has
        k_first = ok.to(torch.uint8).argmax(0)  # the first edge that qualifies
        e = vk.gather(0, torch.stack([k_first, (k_first + 1) % 3]))  # (2, K) its end points
        eidx = (2 * e[None] + pq).view(-1)  # (P|Q, end 0|1, K)
    P0, P1, Q0, Q1 = xy.view(-1).index_select(0, eidx).view(4, K).unbind(0)
    tt = (P0 + (fq - Q0) / (Q1 - Q0).masked_fill(no, 1.0) * (P1 - P0) - fp) * sgn
    f = (tt - 0.5).masked_fill(no, 0.0)  # > 0: the front triangle reaches into the other pixel; < 0: it
    # leaves part of its own; 0 (no edge crosses): the blend adds 0
    dt = color[0].dtype if split else color.dtype
    args = (f.to(dt), pf, po, torch.where(f.detach() > 0, po, pf))
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

