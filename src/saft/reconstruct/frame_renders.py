"""The shape phase's image side: every frame rendered, compared with its target, and differentiated.

Frames are rendered in chunks (one frame on the CPU, 8 on a GPU: ``render_chunk``). Each chunk's graph is
made and differentiated on its own, so that only one chunk's temporaries live at a time. On the CPU the
chunks are independent work for a pool of threads (``render_threads``): the rasterizer's numba loops release
the GIL and so do torch's kernels. Each frame's render starts as soon as the physics has simulated it (the
rollout's ``on_frame``), so that on a machine with a core to spare the renders run beside the physics' forward
pass instead of after it. The result does not depend on the number of threads, bit for bit: every chunk is
differentiated against its own leaves, and its gradients are then passed on, in chunk order, through the
same slice and conversion nodes that one graph over all chunks would have accumulated them through.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import torch

from saft.reconstruct.losses import image_loss, silhouette_loss
from saft.reconstruct.silhouette_reach import silhouette_weights

_POOLS: dict[int, ThreadPoolExecutor] = {}


def render_chunk(device) -> int:
    """Frames rendered per chunk. On a GPU a batch of 8 fills the device; on a CPU one frame at a time is
    cheaper per frame (R1's 700 x 800, forward + backward: ~60 ms a frame alone, ~115 ms a frame in a batch
    of 8, whose large temporaries miss the caches and are paged in and out by the allocator; BENCHMARKS.md)."""
    return 1 if torch.device(device).type == "cpu" else 8


def render_threads(requested: int, device) -> int:
    """Threads that render chunks at once: `requested` (run.render_threads) when > 0; 0 = automatic: every
    core up to 4 on the CPU, one on a GPU (its kernels queue on one stream). Measured on 2 cores only (the
    shape phase −20 to −40 %, BENCHMARKS.md); the cap is a guess: the Python side of each render holds the
    GIL, so many more threads would mostly wait for it."""
    if requested > 0:
        return requested
    if torch.device(device).type != "cpu":
        return 1
    return max(1, min(4, os.cpu_count() or 1))


def _pool(threads: int) -> ThreadPoolExecutor:
    pool = _POOLS.get(threads)
    if pool is None:
        pool = _POOLS[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="saft-render")
    return pool


def _chunk(ctx, cfg, positions, light, texture, targets, weights, want_depth, scale):
    """One chunk: (image loss, silhouette loss, depths or None, d loss / d positions, d loss / d light)."""
    pos = positions.detach().requires_grad_(True)
    lit = None if light is None else light.detach().requires_grad_(light.requires_grad)
    out = ctx.render(pos, texture, lit)
    depths = list(out.depth.detach()) if want_depth else None
    rgb, mask = out.rgb, out.mask
    if cfg.hard_coverage:
        covered = (out.rast[..., 3] > 0).to(rgb.dtype)
        rgb, mask = rgb * covered.unsqueeze(-1), mask * covered
    l_img = image_loss(rgb, targets[0]) * scale
    l_sil = silhouette_loss(mask, targets[1], weights) * scale
    total = cfg.lambda_image * l_img + cfg.lambda_sil * l_sil
    g_pos = g_light = None
    if total.requires_grad:
        leaves = [pos] + ([lit] if lit is not None and lit.requires_grad else [])
        grads = torch.autograd.grad(total, leaves, allow_unused=True)
        g_pos = grads[0]
        g_light = grads[1] if len(grads) > 1 else None
    return float(l_img.detach()), float(l_sil.detach()), depths, g_pos, g_light


class FrameRenders:
    """The renders of one epoch's frames start.. (n_win of them): started as the physics finishes each frame
    (``frame_ready``, the rollout's on_frame) when frames are rendered one at a time on a pool of threads,
    the rest in ``finish``, which also passes the gradients on."""

    def __init__(self, ctx, cfg, light: torch.Tensor | None, texture: torch.Tensor, start: int, n_win: int,
                 reach: float, want_depth: bool, threads: int = 1):
        self.ctx, self.cfg, self.light, self.texture, self.start = ctx, cfg, light, texture, start
        self.reach, self.want_depth, self.threads = reach, want_depth, threads
        batch = render_chunk(ctx.device)
        self.n_win = n_win
        self.spans = [(lo, min(n_win, lo + batch)) for lo in range(0, n_win, batch)]
        self.streaming = threads > 1 and batch == 1 and n_win > 1
        self.futures: dict = {}

    def _job(self, lo: int, hi: int, positions: torch.Tensor) -> tuple:
        ctx, s = self.ctx, self.start
        targets = (ctx.target_rgb[s + lo:s + hi], ctx.target_mask[s + lo:s + hi])
        weights = silhouette_weights(ctx.target_mask, s + lo, s + hi, self.reach, self.cfg.sil_reach_gain)
        return (ctx, self.cfg, positions, self.light, self.texture, targets, weights, self.want_depth,
                (hi - lo) / self.n_win)

    def frame_ready(self, frame: int, positions: torch.Tensor) -> None:
        """The rollout's on_frame: window frame `frame` is simulated; render it now on the pool."""
        if self.streaming and 0 <= frame < self.n_win and frame not in self.futures:
            pos = positions.detach().to(device=self.ctx.device, dtype=torch.float32)[None]
            self.futures[frame] = _pool(self.threads).submit(_chunk, *self._job(frame, frame + 1, pos))

    def finish(self, pos_leaf: torch.Tensor):
        """Render what was not started and wait for every chunk; add the image and silhouette losses' gradients
        into pos_leaf.grad (pos_leaf: the frames' positions, a leaf on the render device) and, through the light
        (a differentiable copy of the learned light, or None), into the light. Returns ({"image",
        "silhouette"}: the losses, averaged over the frames) and the depth maps, one (H, W) per frame when asked
        for (else an empty list)."""
        pending = [(lo, hi) for lo, hi in self.spans if lo not in self.futures]
        jobs = [self._job(lo, hi, pos_leaf[lo:hi]) for lo, hi in pending]
        if self.threads > 1 and len(jobs) > 1:
            done = list(_pool(self.threads).map(lambda job: _chunk(*job), jobs))
        else:
            done = [_chunk(*job) for job in jobs]
        results = dict(zip((lo for lo, _ in pending), done))
        sums = {"image": 0.0, "silhouette": 0.0}
        depths = []
        for lo, hi in self.spans:
            l_img, l_sil, d, g_pos, g_light = results[lo] if lo in results else self.futures[lo].result()
            sums["image"] += l_img
            sums["silhouette"] += l_sil
            if d is not None:
                depths.extend(d)
            # in chunk order, through pos_leaf's slice and the light's conversion: the accumulation of one graph
            if g_pos is not None:
                torch.autograd.backward(pos_leaf[lo:hi], g_pos)
            if g_light is not None:
                torch.autograd.backward(self.light, g_light)
        return sums, depths


__all__ = ["FrameRenders", "render_chunk", "render_threads"]
