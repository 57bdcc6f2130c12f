"""A backtrack's rate cut kept to the frames it was made on: frames added later start at the full rate (issue 29;
not in the paper; shape.backtrack_new_frames, on by default).

The step guard (saft.reconstruct.step_guard) cuts every learning rate for the rest of the run when an epoch's
loss jumps. A cut made early, while the first frames are fitted, then also slows every frame added after it: on
Newton's appearance clips (a flat cloth in a breeze, a gust late in the clip) a cut at frame 9-13 leaves the
gust's frames, added 10-20 frames later, with half the rate for their few epochs each; they fall behind the
billow and the final all-frame epochs do not bring them back (BENCHMARKS.md, "Newton's appearance clips: why
the gust is lost…").

With the option on, a cut applies to the per-frame accelerations (shape_phase.ShapeParams.vertex_accel and
field_accel, window_hold.per_frame) of the transitions in use when it was made; a transition that comes into use
later is stepped without the cuts made before it. Every other parameter (stiffnesses, the constant
acceleration, anchors, light, v0, drag) keeps the guard's global rate, as before. Adam's step is its rate times
a function of its moments, so a row's step scaled by a factor is that row stepped at that factor times the rate.
Where every transition in use carries the same cuts (no cut yet, or cuts made only with all of them in use)
the step is the usual one, bit for bit.
"""

from __future__ import annotations

import torch

from saft.reconstruct.optim import ClippedAdam
from saft.reconstruct.step_guard import StepGuard
from saft.reconstruct.window_hold import per_frame


def row_boost(guard: StepGuard, frames: int, rows: int) -> torch.Tensor | None:
    """(rows,) float64: the factor of each transition's step over the guard's global rate while `frames` frames
    are in use: 1 / decay for every cut made before the transition came into use (transition r, from frame r
    to r + 1, is in use from `r + 2` frames on; a cut made with f frames in use covers the rows below f - 1).
    None where it is 1 for every row in use (the usual step), and where the guard raises its rate again after
    calm epochs (shape.backtrack_recover_epochs > 0: its cuts do not last, the rows' rates follow it)."""
    if guard.decay <= 0 or guard.recover_after > 0:   # a rate raised again after calm epochs: cuts do not last
        return None
    boost = torch.ones(rows, dtype=torch.float64)
    for f in guard.cut_frames:
        boost[max(f - 1, 0):] /= guard.decay
    in_use = max(min(frames - 1, rows), 0)
    if bool((boost[:in_use] == 1.0).all()):
        return None
    return boost


def step(optimizer: ClippedAdam, params, guard: StepGuard, frames: int, on: bool) -> None:
    """optimizer.step(), with each per-frame row's update times row_boost where the option is `on` and the
    rows' cuts differ. `params`: a shape_phase.ShapeParams."""
    rows = params.vertex_accel.shape[0]
    boost = row_boost(guard, frames, rows) if on else None
    if boost is None:
        optimizer.step()
        return
    tensors = per_frame(params)
    before = [t.detach().clone() for t in tensors]
    optimizer.step()
    with torch.no_grad():
        for t, b in zip(tensors, before):
            scale = boost.to(device=t.device, dtype=t.dtype).view(-1, *([1] * (t.dim() - 1)))
            t.copy_(b + (t - b) * scale)


__all__ = ["row_boost", "step"]
