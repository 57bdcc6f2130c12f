"""FD(T): the smoothness prior of a texture (paper's supplement), shared by phase 1's fit on frame 0
(saft.reconstruct.texture_phase) and phase 3's refit on several frames (saft.appearance.texture_frames)."""

from __future__ import annotations

import torch


def finite_difference_smoothness(texture: torch.Tensor) -> torch.Tensor:
    """FD(T): mean L1 norm (over channels) of horizontal plus vertical neighbour differences of an (H, W, C)
    image."""
    dx = (texture[:, 1:] - texture[:, :-1]).abs().sum(dim=-1).mean()
    dy = (texture[1:] - texture[:-1]).abs().sum(dim=-1).mean()
    return dx + dy


__all__ = ["finite_difference_smoothness"]
