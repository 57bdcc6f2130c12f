"""Losses and regularizers of the texture and shape phases (paper sections 3.3.1–3.3.2)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def image_loss(rendered: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared RGB error over all pixels and channels, averaged over frames: (F, H, W, 3) each.
    (F.mse_loss: one fused op each way, where the written-out square and mean cost a GPU three kernels
    forward and four backward per render.)"""
    return F.mse_loss(rendered, target)


def silhouette_loss(mask: torch.Tensor, target_mask: torch.Tensor,
                    weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error of the antialiased coverage against the target mask: (F, H, W) each; with
    `weight` (F, H, W) each pixel's squared error weighs that much (saft.reconstruct.silhouette_reach)."""
    if weight is None:
        return F.mse_loss(mask, target_mask)
    return (weight * (mask - target_mask) ** 2).mean()


def force_regularizer(accel: torch.Tensor, positions: torch.Tensor, camera_center: torch.Tensor,
                      along_weight: float = 0.0) -> torch.Tensor:
    """R_F: mean over frames and vertices of |F − (1 − w) (F·d) d|, d the unit direction from the camera to
    the vertex; w = along_weight: 0 (the paper) leaves the part along the viewing ray free, 1 penalises the
    whole vector.

    accel: (F, V, 3) the per-vertex, per-frame external accelerations; positions: (F, V, 3) the vertex
    positions the directions are taken at (the CURRENT simulated positions of the frames those forces
    produce; detached: the directions are a weighting, not something to optimize).
    """
    d = positions.detach() - camera_center.to(positions)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    d = d.to(accel.dtype)
    along = (accel * d).sum(dim=-1, keepdim=True) * d
    return (accel - (1.0 - along_weight) * along).norm(dim=-1).mean()
