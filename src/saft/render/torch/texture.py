"""texture: bilinear lookup with trilinear mip-mapping (grid_sample per level on the pixels that use it),
and the one box-filter mip-pyramid builder (down2 and its adjoint) that the fused path uses too."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from saft.render.torch.rows import scatter_rows


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
        return scatter_rows(vals, sel_all, B * H * W).reshape(B, H, W, C)
    return vals.reshape(B, H, W, C)


class _PyramidFn(torch.autograd.Function):
    """Mip levels 1..n−1 of an NCHW (N = 1) texture from the one pyramid builder, down2; the backward
    spreads each level's gradient back to level 0 with down2's adjoint (cheaper than autograd)."""

    @staticmethod
    def forward(ctx, t0, n_levels):
        levels = [t0[0]]
        for _ in range(n_levels - 1):
            levels.append(down2(levels[-1]))
        ctx.shapes = [t.shape for t in levels]
        return tuple(t[None] for t in levels[1:])

    @staticmethod
    def backward(ctx, *grads):
        shapes = ctx.shapes
        acc = None
        for lvl in range(len(shapes) - 1, 0, -1):
            g = grads[lvl - 1]
            if g is not None:
                acc = g[0] if acc is None else acc + g[0]
            if acc is not None:
                acc = down2_adjoint_add_(acc.new_zeros(shapes[lvl - 1]), acc)
        return (None if acc is None else acc[None]), None


def mip_count(h: int, w: int) -> int:
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
        max_levels = mip_count(Ht, Wt)
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


def down2(t: torch.Tensor) -> torch.Tensor:
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


def down2_adjoint_add_(acc: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """acc += _down2_adjoint(g, acc.shape), in place with strided adds (no upsampled temporary)."""
    _, h, w = acc.shape
    _, h2, w2 = g.shape
    fy, fx = (2 if h >= 2 else 1), (2 if w >= 2 else 1)
    g = g * (1.0 / (fy * fx))
    for oy in range(fy):
        for ox in range(fx):  # add_ on the view (`acc[...] += g` would also copy the view onto itself)
            acc[:, oy:h2 * fy:fy, ox:w2 * fx:fx].add_(g)
    return acc


def down2_hwc(t: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """down2 of an (h, w, C) level, (h/2, w/2, C) contiguous (or written into out); even sizes without
    small-dimension strided operations (rows of 2C floats are contiguous in HWC memory)."""
    h, w, C = t.shape
    if h >= 2 and w >= 2 and h % 2 == 0 and w % 2 == 0 and t.is_contiguous():
        r = t.view(h // 2, 2, w // 2, 2 * C)
        r = r[:, 0] + r[:, 1]
        return torch.mul(r[..., :C] + r[..., C:], 0.25, out=out)
    d = down2(t.permute(2, 0, 1)).permute(1, 2, 0)
    return d.contiguous() if out is None else out.copy_(d)


def down2_adjoint_add_hwc_(acc: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """acc (h, w, C) += adjoint of down2_hwc applied to g (h/2, w/2, C), in place."""
    h, w, C = acc.shape
    if h >= 2 and w >= 2 and h % 2 == 0 and w % 2 == 0 and acc.is_contiguous():
        g2 = torch.cat([g, g], dim=-1).mul_(0.25)  # (h/2, w/2, 2C): both columns of a pair
        a = acc.view(h // 2, 2, w // 2, 2 * C)
        a[:, 0].add_(g2)  # add_ on the views: `a[:, 0] += g2` would also copy the view onto itself, and
        a[:, 1].add_(g2)  # one broadcast add of g over the 2×2 blocks is 10× slower on CPU (measured)
        return acc
    down2_adjoint_add_(acc.permute(2, 0, 1), g.permute(2, 0, 1))
    return acc

