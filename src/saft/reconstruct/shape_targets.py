"""What the shape phase derives from the video once, before its epochs: the point tracks of the template's
vertices (saft.reconstruct.tracks) and the chamfer silhouette term's distance maps
(saft.reconstruct.silhouette_chamfer)."""

from __future__ import annotations

import torch

from saft.reconstruct.config import ShapeConfig
from saft.reconstruct.context import PhaseContext
from saft.reconstruct.silhouette_chamfer import MaskDistances, boundary_edges, mask_distances
from saft.reconstruct.tracks import VertexTracks, compute_vertex_tracks


def shape_tracks(ctx: PhaseContext, cfg: ShapeConfig, texture: torch.Tensor, template: torch.Tensor) -> VertexTracks | None:
    """Point tracks of `template`'s vertices (on the physics device) through the targets, or None when the
    track loss is off."""
    if cfg.lambda_track <= 0 or ctx.target_rgb.shape[0] < 2:
        return None
    with torch.no_grad():
        depth0 = ctx.render(ctx.template_positions[None].to(torch.float32), texture).depth[0]
    return compute_vertex_tracks(ctx.target_rgb, ctx.target_mask, template, ctx.camera, depth0,
                                 cfg.track_fb_threshold, cfg.track_reanchor_radius, cfg.track_jump_ratio,
                                 cfg.track_jump_floor, cfg.track_drift, cfg.track_drift_scale,
                                 cfg.track_drift_median_ratio)


def shape_chamfer(ctx: PhaseContext, cfg: ShapeConfig, device) -> tuple[MaskDistances, torch.Tensor] | None:
    """The chamfer silhouette term's targets (distance maps, contours; on `device`) and the mesh's border
    edges, or None when it is off."""
    if cfg.lambda_chamfer <= 0 and cfg.lambda_chamfer_cover <= 0:
        return None
    edges = torch.as_tensor(boundary_edges(ctx.triangles.cpu().numpy()), device=device)
    return mask_distances(ctx.target_mask.cpu().numpy(), device=device), edges
