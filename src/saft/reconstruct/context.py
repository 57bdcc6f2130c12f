"""What every phase of a run shares: device, targets, the renderer, progress, log and checkpointing."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from saft.reconstruct.checkpoint import Interrupted
from saft.reconstruct.progress import EpochLog, Progress
from saft.scene.camera import Camera


@dataclass
class PhaseContext:
    device: torch.device
    camera: Camera                     # the working camera (crop and scale applied)
    template_positions: torch.Tensor   # (V, 3) float64 on device
    triangles: torch.Tensor            # (T, 3) int32 on device
    uvs: torch.Tensor                  # (V, 2) float32 on device
    target_rgb: torch.Tensor           # (N, H, W, 3) float32 sRGB on device
    target_mask: torch.Tensor          # (N, H, W) float32 on device
    rasterizer: object
    progress: Progress
    log: EpochLog
    # Called after every epoch with (phase, epochs done, a function returning the phase's state); it
    # writes the checkpoint when due and raises Interrupted after Ctrl-C.
    on_epoch: Callable[[str, int, Callable[[], dict]], None]

    def render(self, vertices: torch.Tensor, texture: torch.Tensor):
        from saft.render import render_cloth

        return render_cloth(vertices, self.triangles, self.uvs, texture, self.camera, rasterizer=self.rasterizer)

    def epoch_done(self, phase: str, epochs_done: int, state_fn: Callable[[], dict]) -> None:
        self.on_epoch(phase, epochs_done, state_fn)


def to_device_targets(rgb: np.ndarray, mask: np.ndarray, device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).to(device),
            torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32)).to(device))


__all__ = ["PhaseContext", "Interrupted", "to_device_targets"]
