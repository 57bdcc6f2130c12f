"""texture_fast: render_cloth's trilinear clamp-mode texture lookup, structure-of-arrays, in a fixed number
of ops: every pixel reads its two mip levels (lo and lo + 1) at once from one flat pyramid (all levels in
one buffer, each in the caller's HWC layout), so that neither the op count nor the host syncs grow with the
number of levels in use. Written by hand (torch has no mip-mapped lookup; grid_sample per level is the
reference, saft.render.torch.texture.texture_compact, tested equal).
"""

from __future__ import annotations

import weakref

import torch

from saft.render.torch import texture_numba
from saft.render.torch.rows import const
from saft.render.torch.texture import down2_adjoint_add_hwc_, down2_hwc, mip_count

_GEOMETRY: dict = {}
_WORKSPACE: dict = {}
_PYRAMID: list = [None]  # (weakref to the texture, its _version, n_levels, flat pyramid): the last one made
USE_NUMBA = True  # CPU tensors take texture_numba's loops (tests switch it off to check the torch path)


def _geometry(Ht: int, Wt: int, C: int, n_levels: int, like: torch.Tensor):
    """Per mip level of an (Ht, Wt, C) texture: sizes [(h, w)], flat offsets (in texels) and two device
    tables, made once per shape: gf (4, n) float (w, h, max(w − 2, 0), max(h − 2, 0)) and gi (4, n) int32,
    the texel offsets of the four bilinear taps (00, 01, 10, 11) plus the level's offset (clamp-to-edge:
    a level one texel wide or high repeats its only column or row)."""
    key = (Ht, Wt, C, n_levels, like.dtype, like.device)
    g = _GEOMETRY.get(key)
    if g is None:
        sizes, offs, h, w, o = [], [], Ht, Wt, 0
        for _ in range(n_levels):
            sizes.append((h, w))
            offs.append(o)
            o += h * w
            h, w = max(1, h // 2), max(1, w // 2)
        gf = torch.tensor([[w for _, w in sizes], [h for h, _ in sizes], [max(w - 2, 0) for _, w in sizes],
                           [max(h - 2, 0) for h, _ in sizes]], dtype=like.dtype, device=like.device)
        taps = []
        for (h, w), base in zip(sizes, offs):
            ox, oy = (1 if w >= 2 else 0), (w if h >= 2 else 0)
            taps.append([base, base + ox, base + oy, base + oy + ox])
        gi = torch.tensor(taps, dtype=torch.int32, device=like.device).T.contiguous()
        g = _GEOMETRY[key] = (sizes, offs, o, gf, gi)
    return g


def _workspace(name: str, n: int, like: torch.Tensor) -> torch.Tensor:
    """A buffer of n elements of like's dtype and device kept for the next call of the same size: on CPU a
    fresh multi-megabyte buffer per call costs about one page fault per 4 kB (measured: ~1000 per
    render at 240x320). One per name; a new size replaces it."""
    key = (name, like.dtype, like.device)
    buf = _WORKSPACE.get(key)
    if buf is None or buf.numel() != n:
        buf = _WORKSPACE[key] = like.new_empty(n)
    return buf


def _pyramid(tex: torch.Tensor, sizes, offs, total: int) -> torch.Tensor:
    """All levels of tex's box-filtered mip pyramid in one flat buffer (level k at offs[k] texels, HWC).
    For a texture without gradient (the shape phase renders every frame with the same one) the last
    pyramid is kept while the texture is unchanged: same object, same _version (a change through .data
    would not be seen; gradcheck makes such changes to the inputs it differentiates, hence no caching of
    a texture that requires grad, which the texture phase changes every step anyway)."""
    C = tex.shape[2]
    if len(sizes) == 1 and tex.is_contiguous():
        return tex.detach().reshape(-1)
    cache = not tex.requires_grad
    hit = _PYRAMID[0]
    if cache and hit is not None and hit[0]() is tex and hit[1] == tex._version and hit[2] == len(sizes):
        return hit[3]
    key = (weakref.ref(tex), tex._version, len(sizes))
    tex = tex.detach()
    if cache:
        flat = tex.new_empty(total * C)
    else:  # rewritten by every call (the backward does not read it)
        flat = _workspace("pyramid", total * C, tex)
    flat[:tex.numel()].copy_(tex.reshape(-1))
    for k in range(1, len(sizes)):  # each level from the one before, into its slice of the flat buffer
        (h0, w0), (h, w) = sizes[k - 1], sizes[k]
        down2_hwc(flat[offs[k - 1] * C:(offs[k - 1] + h0 * w0) * C].view(h0, w0, C),
                  out=flat[offs[k] * C:(offs[k] + h * w) * C].view(h, w, C))
    if cache:
        _PYRAMID[0] = key + (flat,)
    return flat


class _TexFn(torch.autograd.Function):
    """Trilinear (or bilinear) lookup: tex (Ht, Wt, C), u, v (P,), lo (P,) int64 and frac (P,) (or None:
    level 0 only) → (C, P). Taps and weights (4, levels, P), values (C, 4, levels, P), every index and
    weight computed in a contiguous layout (a broadcast add into a transposed one costs more than the
    lookup on CPU). Hand-written backward:
    one index_add into the flat pyramid's gradient, the pyramid's adjoint, and the coordinate gradient."""

    @staticmethod
    def forward(ctx, tex, u, v, lo, frac, n_levels):
        Ht, Wt, C = tex.shape
        P = u.shape[0]
        sizes, offs, total, gf, gi = _geometry(Ht, Wt, C, n_levels, u)
        flat = _pyramid(tex, sizes, offs, total)  # tex itself: the cache knows it by identity
        if USE_NUMBA and u.device.type == "cpu":
            return _numba_forward(ctx, flat, tex, u, v, lo, frac, n_levels, (sizes, offs, total, C, gf, gi))
        if lo is None:
            L = torch.zeros(1, P, dtype=torch.int64, device=u.device)
        else:  # the upper level of a pixel on the last one gets weight frac = 0
            L = torch.stack([lo, (lo + 1).clamp_(max=n_levels - 1)])
        nl = L.shape[0]
        Lf = L.view(-1)
        w_, h_, wm, hm = gf.index_select(1, Lf).view(4, nl, P).unbind(0)
        x = u * w_ - 0.5
        y = v * h_ - 0.5
        insx = (x > 0) & (x < w_ - 1)  # strictly inside: where grid_sample's coordinate gradient is 1
        insy = (y > 0) & (y < h_ - 1)
        x = torch.clamp(x, min=torch.zeros_like(w_), max=w_ - 1)
        y = torch.clamp(y, min=torch.zeros_like(h_), max=h_ - 1)
        x0f = torch.minimum(x.floor(), wm)  # the left/top tap at most at w−2 / h−2 (fx = 1 at the last texel)
        y0f = torch.minimum(y.floor(), hm)
        fx = x - x0f
        fy = y - y0f
        # int32 indices (texel·C + channel < 2**31 up to 8192² RGB): the largest temporaries here, and on
        # CPU every large fresh allocation costs page faults
        idx = (y0f * w_ + x0f).int() + gi.index_select(1, Lf).view(4, nl, P)  # (4 taps, levels, P)
        gx, gy = 1.0 - fx, 1.0 - fy
        bw = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy])  # (4, levels, P)
        if lo is not None:
            bw *= torch.stack([1.0 - frac, frac])
        bw = bw.to(tex.dtype)
        cidx = idx * C + torch.arange(C, dtype=torch.int32, device=u.device).view(C, 1, 1, 1)
        tv = flat.index_select(0, cidx.view(-1)).view(C, 4, nl, P)
        val = (tv * bw).sum(1)
        out = val[:, 0] if nl == 1 else val[:, 0] + val[:, 1]
        ctx.save_for_backward(cidx, fx, fy, insx, insy, bw, tv, w_, h_, frac if lo is not None else None)
        ctx.geo = (sizes, offs, total, C)
        ctx.needs = ctx.needs_input_grad[:3]
        ctx.uv_dtype = u.dtype
        ctx.numba = False
        return out

    @staticmethod
    def backward(ctx, g):
        need_tex, need_u, need_v = ctx.needs
        if ctx.numba:
            return _numba_backward(ctx, g)
        cidx, fx, fy, insx, insy, bw, tv, w_, h_, frac = ctx.saved_tensors
        sizes, offs, total, C = ctx.geo
        g = g.contiguous()  # (C, P)
        g_tex = gu = gv = None
        if need_tex:
            # into a workspace zeroed in place (a fresh 4 MB buffer per call costs ~1000 page faults on
            # CPU), then level 0 copied out as the texture's gradient
            gflat = _workspace("grad", total * C, g).zero_()
            gflat.index_add_(0, cidx.view(-1), (bw * g[:, None, None]).view(-1))
            g_tex = _texture_grad(gflat, sizes, offs, C)
        if need_u or need_v:
            gd = (tv * g[:, None, None]).sum(0).to(fx.dtype)  # (4, levels, P): <g, texel k>
            if frac is not None:
                gd *= torch.stack([1.0 - frac, frac])
            g0, g1, g2, g3 = gd.unbind(0)

            def level_sum(d):
                return d[0] if d.shape[0] == 1 else d[0] + d[1]

            if need_u:  # d/dx of the blend: (1−fy)(t01 − t00) + fy (t11 − t10)
                gu = level_sum(((1.0 - fy) * (g1 - g0) + fy * (g3 - g2)) * (w_ * insx.to(fx.dtype)))
            if need_v:
                gv = level_sum(((1.0 - fx) * (g2 - g0) + fx * (g3 - g1)) * (h_ * insy.to(fx.dtype)))
        return g_tex, gu, gv, None, None, None


def _texture_grad(gflat: torch.Tensor, sizes, offs, C: int) -> torch.Tensor:
    """The texture's gradient from its flat pyramid's (gflat, changed in place): each level's adjoint added
    into the one below, coarse to fine, then level 0 copied out."""
    for k in range(len(sizes) - 1, 0, -1):
        (h0, w0), (h, w) = sizes[k - 1], sizes[k]
        down2_adjoint_add_hwc_(gflat[offs[k - 1] * C:(offs[k - 1] + h0 * w0) * C].view(h0, w0, C),
                               gflat[offs[k] * C:(offs[k] + h * w) * C].view(h, w, C))
    return gflat[:sizes[0][0] * sizes[0][1] * C].view(sizes[0][0], sizes[0][1], C).clone()


def _numba_forward(ctx, flat, tex, u, v, lo, frac, n_levels, geo):
    """_TexFn.forward on CPU tensors by texture_numba.lookup; saves only the coordinates for the adjoint."""
    texture_numba.load()
    C = tex.shape[2]
    u, v = u.detach().contiguous(), v.detach().contiguous()
    lo = torch.empty(0, dtype=torch.int64) if lo is None else lo.contiguous()
    frac = u.new_empty(0) if frac is None else frac.detach().contiguous()
    gf, gi = geo[4].double().numpy(), geo[5].numpy()
    out = torch.empty(C, u.shape[0], dtype=tex.dtype)
    texture_numba.lookup(flat.numpy(), C, gf, gi, u.numpy(), v.numpy(), lo.numpy(), frac.numpy(), n_levels,
                         out.numpy())
    ctx.needs = ctx.needs_input_grad[:3]
    if not (ctx.needs[1] or ctx.needs[2]):
        flat = flat.new_empty(0)  # the adjoint reads the texels only for the coordinates' gradient
    elif tex.requires_grad:
        flat = flat.clone()  # a texture with gradient has its pyramid in a workspace the next call rewrites
    ctx.save_for_backward(flat, u, v, lo, frac)
    ctx.geo = geo[:4] + (gf, gi, n_levels)
    ctx.numba = True
    return out


def _numba_backward(ctx, g):
    need_tex, need_u, need_v = ctx.needs
    flat, u, v, lo, frac = ctx.saved_tensors
    sizes, offs, total, C, gf, gi, n_levels = ctx.geo
    g = g.contiguous()
    gflat = _workspace("grad", total * C, g).zero_() if need_tex else g.new_empty(0)
    gu, gv = torch.empty_like(u), torch.empty_like(v)
    texture_numba.lookup_adjoint(flat.numpy(), C, gf, gi, u.numpy(), v.numpy(), lo.numpy(), frac.numpy(),
                                 n_levels, g.numpy(), gflat.numpy(), gu.numpy(), gv.numpy(), need_tex,
                                 need_u or need_v)
    g_tex = _texture_grad(gflat, sizes, offs, C) if need_tex else None
    return g_tex, gu if need_u else None, gv if need_v else None, None, None, None


def texture_fast(tex: torch.Tensor, u: torch.Tensor, v: torch.Tensor, uv_da: torch.Tensor | None = None,
                 max_mip_level: int | None = None) -> torch.Tensor:
    """texture_compact(tex, stack([u, v], 1), uv_da.T, 'clamp', max_mip_level).T for render_cloth, in
    value and gradient, structure-of-arrays: tex (Ht, Wt, C), u, v (P,), uv_da (4, P) or None → (C, P).
    Differentiable w.r.t. tex, u and v. One host sync (the number of levels in use)."""
    Ht, Wt, C = tex.shape
    if u.shape[0] == 0:
        return u.new_zeros(C, 0, dtype=tex.dtype)
    lo = frac = None
    n_levels = 1
    max_levels = mip_count(Ht, Wt)
    if max_mip_level is not None:
        max_levels = min(max_levels, int(max_mip_level) + 1)
    if uv_da is not None and max_levels > 1:
        with torch.no_grad():  # footprint² along screen x and y: (du/dX·Wt)² + (dv/dX·Ht)², …
            m2 = (uv_da.view(2, 2, -1) * const((Wt, Ht), uv_da).view(2, 1, 1)).square_().sum(0).amax(0)
            lod = (0.5 * torch.log2(m2.clamp_min(1e-30))).clamp_(0.0, max_levels - 1)
            n_levels = int(lod.ceil().max()) + 1  # levels lo and lo + 1 where frac > 0
            if n_levels > 1:
                lo_f = lod.floor()
                frac = (lod - lo_f).to(u.dtype)
                lo = lo_f.long()
    return _TexFn.apply(tex, u, v, lo, frac, n_levels)
