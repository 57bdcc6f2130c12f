"""antialias: nvdiffrast's analytic scheme — for each pair of horizontally or vertically adjacent pixels
with different triangles, a silhouette edge (mesh boundary, or an edge between a front- and a back-facing
triangle: folds) of the nearer triangle that crosses the segment between the two centres blends the
colours in proportion to where it crosses; the blend weight depends on the edge's projected end points,
which gives the silhouette gradients with respect to the positions.
"""

from __future__ import annotations

import math

import torch

from saft.render.topology import edge_neighbors
from saft.render.torch.raster import W_EPS
from saft.render.torch.rows import check_pos_tri


def _screen_xy(pos: torch.Tensor, H: int, W: int):
    w = pos[..., 3]
    w = torch.where(w.abs() < W_EPS, torch.full_like(w, W_EPS), w)
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
    return antialias_core(color, tid_img, depth_img, pos, tri)


def antialias_core(color, tid_img, depth_img, pos, tri, split=False):
    pos, tri = check_pos_tri(pos, tri)
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

