"""What a windowed shape epoch (shape.window > 0, start > 0) must leave as it is.

A window starts from stored, detached states, simulated with the parameters of the frames before it and
with frame 0's state; the optimizer must not move those. `params` below: a ShapeParams
(saft.reconstruct.shape_phase, which imports this module).
"""

from __future__ import annotations

import torch


def per_frame(params) -> list[torch.Tensor]:
    """The parameters indexed by frame transition."""
    return [params.vertex_accel] + ([params.field_accel] if params.field_accel is not None else [])


def initial(params) -> list[torch.Tensor]:
    """Frame 0's state (the learned velocity, saft.reconstruct.initial_velocity): held in windows, as per_frame."""
    return [] if params.v0_field is None else [params.v0_field]


def outside_window(params, start: int) -> tuple[list[torch.Tensor], list[torch.Tensor]] | None:
    """The accelerations a windowed epoch (start > 0) must leave as they are: those of the frames before the
    window, with which the stored states were simulated. Without this, Adam's momentum keeps moving the
    accelerations of frames that just left the window (by up to ~10 learning rates in all, with no gradient)
    and the stored states drift from what a full pass gives (BENCHMARKS.md: 3.17 -> 2.05 mean CD2 on
    bench_scaling's 50 frames). Y, B, S and C stay free: held to the full passes, they cost far more (14.6)
    than the slight staleness of the states their small steps cause. Returned as (per_frame's rows before
    the window, initial's tensors)."""
    if start <= 0:
        return None
    return [t[:start].detach().clone() for t in per_frame(params)], [t.detach().clone() for t in initial(params)]


def restore_outside_window(params, start: int,
                           keep: tuple[list[torch.Tensor], list[torch.Tensor]] | None) -> None:
    if keep is not None:
        frames, first = keep
        with torch.no_grad():
            for t, k in zip(per_frame(params), frames):
                t[:start] = k
            for t, k in zip(initial(params), first):
                t.copy_(k)


__all__ = ["initial", "outside_window", "per_frame", "restore_outside_window"]
