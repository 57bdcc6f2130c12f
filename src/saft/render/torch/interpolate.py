"""interpolate: vertex attributes at the covered pixels (gathers on the covered pixels only, autograd)."""

from __future__ import annotations

import torch

from saft.render.torch.rows import gather_rows, scatter_rows


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
    r = gather_rows(rast.reshape(-1, 4), pix)
    vid = tri[tid]
    if attr.shape[0] == 1:
        a = attr[0][vid]  # (P, 3, C)
    else:
        b = torch.div(pix, H * W, rounding_mode="floor")
        a = attr.reshape(-1, C)[vid + (b * V)[:, None]]
    u, v = r[:, 0:1], r[:, 1:2]
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    vals = a2 + u * (a0 - a2) + v * (a1 - a2)
    out = scatter_rows(vals, pix, B * H * W).reshape(B, H, W, C)
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

