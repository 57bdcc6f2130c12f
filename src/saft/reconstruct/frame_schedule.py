"""Which frames the shape phase uses at each epoch: the progressive schedule, fixed or driven by convergence.

The paper's schedule is fixed: the first frames for a few epochs, then one more frame every
`add_frame_every` epochs, then `final_epochs` epochs with all frames. A frame whose motion is hard to
explain (a fast swing, a fold) is not yet fitted when the next one is added, and every later frame
inherits the error through the simulation.

With `shape.plateau_max_extra > 0` the schedule waits for the newest frame: after the usual epochs, the
same frames stay in use while the loss still falls, i.e. while the lowest loss of the last two epochs is
more than `shape.plateau_tol` (relative) below the lowest before them, for at most `plateau_max_extra`
more epochs per frame. With 0 (the default) it is exactly the fixed schedule (`shape_schedule`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from saft.reconstruct.config import ShapeConfig, shape_schedule


@dataclass
class FrameSchedule:
    num_frames: int
    cfg: ShapeConfig
    frames: int = 0                     # frames in use now (0: not started)
    epochs_on: int = 0                  # epochs done with them
    extra_total: int = 0                # epochs added by the plateau rule so far
    losses: list[float] = field(default_factory=list)   # losses of the epochs with these frames

    def __post_init__(self):
        if self.frames == 0:
            self.frames = min(self.num_frames, self.first_frames)

    @property
    def first_frames(self) -> int:
        return min(self.num_frames, max(2, self.cfg.initial_frames))

    @property
    def final(self) -> bool:
        """All frames are in use (the final epochs)."""
        return self.frames >= self.num_frames

    @property
    def done(self) -> bool:
        return self.final and self.epochs_on >= self.cfg.final_epochs

    @property
    def just_added(self) -> bool:
        """A frame was added and no epoch has used it yet."""
        return self.epochs_on == 0 and self.frames > self.first_frames

    @property
    def total_epochs(self) -> int:
        """Epochs of the whole phase as far as known now (the fixed schedule plus the extra epochs so far)."""
        return len(shape_schedule(self.num_frames, self.cfg)) + self.extra_total

    def min_epochs(self) -> int:
        if self.final:
            return self.cfg.final_epochs
        if self.frames == self.first_frames:
            return self.cfg.initial_epochs if self.cfg.initial_epochs > 0 else self.cfg.add_frame_every
        return self.cfg.add_frame_every

    def plateaued(self) -> bool:
        if len(self.losses) < 3:
            return False
        recent, before = min(self.losses[-2:]), min(self.losses[:-2])
        return recent >= (1.0 - self.cfg.plateau_tol) * before

    def epoch_done(self, loss: float) -> None:
        """Record an epoch's loss and move on to the next frame when it is time."""
        self.epochs_on += 1
        self.losses.append(float(loss))
        if self.final or self.epochs_on < self.min_epochs():
            return
        extra = self.epochs_on - self.min_epochs()
        if self.cfg.plateau_max_extra > 0 and extra < self.cfg.plateau_max_extra and not self.plateaued():
            self.extra_total += 1
            return
        self.frames += 1
        self.epochs_on = 0
        self.losses = []

    def first_final_epoch(self, epoch: int) -> float:
        """Index of the first all-frame epoch, given the index of the current one (inf before it)."""
        return epoch - self.epochs_on if self.final else float("inf")

    def state_dict(self) -> dict:
        return {"frames": self.frames, "epochs_on": self.epochs_on, "extra_total": self.extra_total,
                "losses": list(self.losses)}

    @classmethod
    def restore(cls, num_frames: int, cfg: ShapeConfig, saved: dict | None, epoch: int) -> "FrameSchedule":
        """From a checkpoint's schedule state, or (older checkpoints) from the fixed schedule at `epoch`."""
        if saved:
            return cls(num_frames, cfg, int(saved["frames"]), int(saved["epochs_on"]), int(saved["extra_total"]),
                       [float(x) for x in saved["losses"]])
        sched = cls(num_frames, cfg)
        fixed = shape_schedule(num_frames, cfg)
        if epoch >= len(fixed):
            sched.frames, sched.epochs_on = num_frames, cfg.final_epochs
        elif epoch > 0:
            sched.frames = fixed[epoch]
            sched.epochs_on = sum(1 for f in fixed[:epoch] if f == fixed[epoch])
        return sched


def window_first_frame(frames: int, epoch: int, final: bool, cfg: ShapeConfig) -> int:
    """First frame an epoch simulates under the windowed schedule (shape.window): 0 (from the template)
    when windows are off, in the final all-frame epochs, on every full_pass_every-th epoch, and while the
    frames in use do not reach past the window; else the frame `window` transitions before the newest."""
    if cfg.window <= 0 or final or (cfg.full_pass_every > 0 and epoch % cfg.full_pass_every == 0):
        return 0
    return max(0, frames - 1 - cfg.window)


def simulated_frames_per_epoch(num_frames: int, cfg: ShapeConfig) -> list[int]:
    """Frames simulated and rendered in each epoch of the fixed schedule (the work of the epoch)."""
    return [f - window_first_frame(f, epoch, f >= num_frames, cfg)
            for epoch, f in enumerate(shape_schedule(num_frames, cfg))]


def lr_factor(epoch: int, first_final: float, cfg: ShapeConfig) -> float:
    """Learning-rate factor: 1 until the final all-frame epochs, then a cosine down to final_lr_fraction."""
    if cfg.final_lr_fraction >= 1.0 or epoch < first_final or cfg.final_epochs <= 1:
        return 1.0
    progress = (epoch - first_final) / (cfg.final_epochs - 1)
    return cfg.final_lr_fraction + (1.0 - cfg.final_lr_fraction) * 0.5 * (1.0 + np.cos(np.pi * progress))


__all__ = ["FrameSchedule", "window_first_frame", "simulated_frames_per_epoch", "lr_factor"]
