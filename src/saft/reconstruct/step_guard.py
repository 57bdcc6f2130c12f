"""Backtracking for the shape phase: a step that made the loss jump is undone and the step size cut.

Adam's steps on the per-vertex accelerations have a fixed size (the learning rate) whatever the curvature,
and an acceleration early in the video moves every later frame: once many frames are in use, a step of
the published size overshoots, and the loss oscillates or climbs from epoch to epoch (measured on R1:
oscillation of ±30 % over the final epochs; with point tracks, a steady climb to 60× the loss). The guard
watches the loss of each epoch against the lowest loss seen with the same frames in use:

- a new lowest loss: the parameters, the optimizer's state and the gradients are kept (a snapshot);
- a loss above `ratio` × the lowest: the snapshot is restored, every learning rate is multiplied by
  `decay` from then on, and the optimizer steps again from the restored point with the smaller rate;
- optionally (`recover_after` > 0, a trust-region-like rule), after that many epochs in a row without a
  backtrack the rate is divided by `decay` again, up to the full rate: a cut made for one hard frame
  then does not slow every later frame.

The snapshot lives in memory only; after --resume the guard starts a new one (its learning-rate scale is
in the checkpoint).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import torch

from saft.reconstruct.optim import ClippedAdam


@dataclass
class StepGuard:
    ratio: float                       # loss / lowest loss that triggers a backtrack (0: guard off)
    decay: float                       # learning-rate factor applied at each backtrack
    recover_after: int = 0             # epochs without a backtrack before the rate is raised again (0: never)
    lr_scale: float = 1.0              # product of the decays (and recoveries) so far
    backtracks: int = 0
    calm: int = 0                      # epochs since the last backtrack or recovery
    frames: int = -1                   # frames in use the lowest loss refers to
    lowest: float = math.inf
    cut_frames: list[int] = field(default_factory=list)   # frames in use at each backtrack (new_frame_rate.py)
    _snapshot: dict | None = field(default=None, repr=False)

    def check(self, frames: int, loss: float, tensors: dict[str, torch.Tensor], optimizer: ClippedAdam) -> bool:
        """Call after an epoch's loss and gradients, before the optimizer's step. Returns True when the
        parameters, gradients and optimizer state were rolled back to the snapshot (and the rate cut)."""
        if self.ratio <= 0 or not math.isfinite(loss):
            return False
        self.calm += 1
        if 0 < self.recover_after <= self.calm and self.lr_scale < 1.0:
            self.lr_scale, self.calm = min(1.0, self.lr_scale / self.decay), 0
        if frames != self.frames:
            self.frames, self.lowest, self._snapshot = frames, math.inf, None
        if loss <= self.lowest:
            self.lowest = loss
            self._snapshot = {
                "params": {k: t.detach().clone() for k, t in tensors.items()},
                "grads": {k: (None if t.grad is None else t.grad.clone()) for k, t in tensors.items()},
                "optimizer": copy.deepcopy(optimizer.state_dict()),
            }
            return False
        if loss <= self.ratio * self.lowest or self._snapshot is None:
            return False
        snap = self._snapshot
        with torch.no_grad():
            for k, t in tensors.items():
                t.copy_(snap["params"][k])
                g = snap["grads"][k]
                t.grad = None if g is None else g.clone()
        optimizer.load_state_dict(copy.deepcopy(snap["optimizer"]))
        self.lr_scale *= self.decay
        self.backtracks += 1
        self.cut_frames.append(int(frames))
        self.calm = 0
        return True

    def state_dict(self) -> dict:
        return {"lr_scale": self.lr_scale, "backtracks": self.backtracks, "calm": self.calm,
                "cut_frames": list(self.cut_frames)}

    def load_state_dict(self, state: dict) -> None:
        self.lr_scale = float(state.get("lr_scale", 1.0))
        self.backtracks = int(state.get("backtracks", 0))
        self.calm = int(state.get("calm", 0))
        self.cut_frames = [int(f) for f in state.get("cut_frames", [])]


__all__ = ["StepGuard"]
