"""Row scatter/gather with hand-written backwards, shared by the torch primitives and the fused path."""

from __future__ import annotations

import torch

_CONSTS: dict = {}


def const(values: tuple, like: torch.Tensor) -> torch.Tensor:
    """A small constant tensor of like's dtype and device, made once (a per-call torch.tensor would be a
    host-to-device copy per frame on a GPU)."""
    key = (values, like.dtype, like.device)
    t = _CONSTS.get(key)
    if t is None:
        t = _CONSTS[key] = torch.tensor(values, dtype=like.dtype, device=like.device)
    return t


def check_pos_tri(pos: torch.Tensor, tri: torch.Tensor):
    if pos.dim() == 2:
        pos = pos[None]
    if pos.dim() != 3 or pos.shape[-1] != 4:
        raise ValueError(f"pos must be (B, V, 4) clip-space positions, got {tuple(pos.shape)}")
    if tri.dim() != 2 or tri.shape[-1] != 3:
        raise ValueError(f"tri must be (T, 3), got {tuple(tri.shape)}")
    return pos, tri.to(device=pos.device, dtype=torch.int64)



class ScatterRows(torch.autograd.Function):
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


def scatter_rows(vals, idx, n):
    return ScatterRows.apply(vals, idx, n)

class GatherRows(torch.autograd.Function):
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


def gather_rows(x, idx):
    return GatherRows.apply(x, idx)


class ScatterPlanar(torch.autograd.Function):
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

