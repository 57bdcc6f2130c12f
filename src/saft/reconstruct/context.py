"""What every phase of a run shares: device, targets, the renderer, progress, log, checkpointing and Ctrl-C.

The phase protocol: a phase reads what it needs from the PhaseContext, calls ctx.epoch_done(phase, epochs,
state_fn) after every epoch (checkpoint when due, then ctx.check_interrupt), or ctx.checkpoint(phase, state)
and ctx.check_interrupt(phase) itself when its optimiser keeps its own epochs (the appearance fit).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from saft.device import DevicePlan
from saft.reconstruct.checkpoint import CheckpointClock, InterruptGuard, Interrupted, save_checkpoint
from saft.reconstruct.progress import EpochLog, Progress
from saft.render import render_cloth
from saft.render.shading import facing_normals, shading_ratio
from saft.scene.camera import Camera


@dataclass
class PhaseContext:
    device: torch.device               # the renders' device (devices.render)
    devices: DevicePlan                # where each part of the run goes (saft.device.plan_devices)
    camera: Camera                     # the working camera (crop and scale applied)
    template_positions: torch.Tensor   # (V, 3) float64 on device (the simulator keeps its copy on devices.physics)
    triangles: torch.Tensor            # (T, 3) int32 on device
    uvs: torch.Tensor                  # (V, 2) float32 on device
    target_rgb: torch.Tensor           # (N, H, W, 3) float32 sRGB on device
    target_mask: torch.Tensor          # (N, H, W) float32 on device
    rasterizer: object
    progress: Progress
    log: EpochLog
    out_dir: Path
    # The run's checkpoint: {"version", "phase", "<phase>_state", results of finished phases, "log", "timings"}.
    state: dict
    timings: dict                      # seconds per phase, accumulated over resumed runs
    guard: InterruptGuard = field(default_factory=InterruptGuard)
    clock: CheckpointClock = field(default_factory=lambda: CheckpointClock(0.0))
    _reference_normals: torch.Tensor | None = field(default=None, repr=False)   # facing normals of the template
    render_threads: int = 1            # shape-phase frames rendered side by side (frame_renders.render_threads)
    # Called after every epoch with (phase, epochs done); returning True acts like Ctrl-C.
    on_epoch: Callable[[str, int], bool | None] | None = None

    def render(self, vertices: torch.Tensor, texture: torch.Tensor, light: torch.Tensor | None = None):
        """render_cloth of (B, V, 3) vertices with the run's texture; with a light vector (3,), shaded relative
        to the template (saft.render.shading: the texture holds frame 0's shading)."""
        shading = None
        if light is not None:
            center = torch.as_tensor(self.camera.center, dtype=vertices.dtype, device=vertices.device)
            if self._reference_normals is None:
                self._reference_normals = facing_normals(self.template_positions[None].to(vertices.dtype),
                                                         self.triangles.long(), center)[0]
            shading = shading_ratio(vertices, self._reference_normals.to(vertices.dtype), self.triangles.long(),
                                    center, light)
        return render_cloth(vertices, self.triangles, self.uvs, texture, self.camera, rasterizer=self.rasterizer,
                            vertex_shading=shading)

    def checkpoint(self, phase: str | None = None, phase_state: dict | None = None) -> None:
        """Write the checkpoint now, with `phase_state` as the state of the running `phase` when given."""
        if phase is not None:
            self.state[f"{phase}_state"] = phase_state
        self.state["log"] = self.log.rows
        self.state["timings"] = self.timings
        began = time.monotonic()
        save_checkpoint(self.out_dir, self.state)
        self.clock.mark(time.monotonic() - began)

    def check_interrupt(self, phase: str, epochs_done: int | None = None) -> None:
        """Raise Interrupted after Ctrl-C (or an on_epoch request); the checkpoint is already written."""
        if self.guard.requested:
            where = f"phase {phase}" if epochs_done is None else f"phase {phase} after epoch {epochs_done}"
            raise Interrupted(f"interrupted in {where}; continue with --resume "
                              f"(checkpoint in {self.out_dir / 'checkpoint'})")

    def epoch_done(self, phase: str, epochs_done: int, state_fn: Callable[[], dict] | None = None) -> None:
        """After every epoch: the on_epoch hook, the checkpoint when due or interrupted, then check_interrupt.
        Without state_fn the phase writes its own checkpoints (also when check_interrupt raises)."""
        if self.on_epoch is not None and self.on_epoch(phase, epochs_done):
            self.guard.requested = True
        if state_fn is not None and (self.guard.requested or self.clock.due()):
            self.checkpoint(phase, state_fn())
        self.check_interrupt(phase, epochs_done)


def to_device_targets(rgb: np.ndarray, mask: np.ndarray, device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).to(device),
            torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32)).to(device))


__all__ = ["PhaseContext", "Interrupted", "to_device_targets"]
