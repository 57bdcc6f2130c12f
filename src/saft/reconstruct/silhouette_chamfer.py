"""A silhouette term with long-range gradients: a chamfer distance between the video's mask and the cloth.

The soft-raster silhouette loss (losses.silhouette_loss) compares coverage pixel by pixel: a misplaced
edge is pulled only by the pixels beside it, with the same force whether it is 1 px or 10 px off. The
chamfer term measures the distance itself, in both directions, with distance transforms of the target
masks computed once (OpenCV):

- outside: every projected template vertex that falls outside the target mask is pulled towards it by
  its distance to the mask (the distance transform of the mask's complement, sampled bilinearly at the
  vertex's projection; 0 on the mask);
- coverage: every pixel on the target silhouette's contour pulls the nearest segment of the projected
  template boundary (the mesh's border edges) towards it.

    L_outside = mean over (frame, vertex) of huber(d_out(π(x_v,t)) / s)
    L_cover   = mean over (frame, contour pixel p) of huber(min_e dist(p, π(e_t)) / s)

s: the image's larger side in pixels (as the track loss), huber with the threshold `huber_delta` pixels.
A crease of a fold is a silhouette edge that is not on the mesh border: its contour pixels pull the
nearest border segment, and the Huber threshold bounds how hard. On the independent one-corner scene the
truth scores a higher L_cover than the reconstruction from frame 15 on (folds), but no vertex of it lies
more than 1 px outside the mask (the reconstruction: up to 172 vertices, 9 px), so the two have separate
weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from saft.reconstruct.tracks import project
from saft.scene.camera import Camera


@dataclass
class MaskDistances:
    outside: torch.Tensor           # (N, 1, H, W) float32: pixels from each pixel to the target mask (0 on it)
    contour: list[torch.Tensor]     # per frame, (P, 2) pixel positions (u, v) on the target silhouette's contour
    scale: float                    # pixels per unit of the loss (the image's larger side)


def mask_distances(target_mask: np.ndarray, max_contour: int = 400, device=None,
                   dtype=torch.float64) -> MaskDistances:
    """Distance maps and contour samples of the target masks (N, H, W) in [0, 1] (thresholded at 0.5); at
    most `max_contour` contour pixels a frame, evenly spaced along the contours."""
    import cv2  # opencv-python-headless, imported lazily as in tracks.py

    outside, contour = [], []
    for m in target_mask:
        on = (m >= 0.5).astype(np.uint8)
        outside.append(cv2.distanceTransform(1 - on, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
        found, _ = cv2.findContours(on, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        pts = (np.concatenate([c.reshape(-1, 2) for c in found]) if found else np.zeros((0, 2))).astype(np.float64)
        if len(pts) > max_contour:
            pts = pts[np.linspace(0, len(pts) - 1, max_contour).round().astype(np.int64)]
        contour.append(torch.as_tensor(pts, dtype=dtype, device=device))
    H, W = target_mask.shape[1:]
    dist = torch.as_tensor(np.stack(outside), dtype=torch.float32, device=device)[:, None]
    return MaskDistances(outside=dist, contour=contour, scale=float(max(H, W)))


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """(B, 2) vertex pairs of the edges that belong to exactly one triangle: the mesh's border."""
    tri = np.asarray(triangles, dtype=np.int64)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def _huber(r: torch.Tensor, d: float) -> torch.Tensor:
    return torch.where(r <= d, 0.5 * r * r, d * (r - 0.5 * d))


def point_segment_distance(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(P, E) distances of points (P, 2) to the segments a → b (E, 2 each)."""
    ab = b - a                                                      # (E, 2)
    ap = points[:, None, :] - a[None]                               # (P, E, 2)
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (ap - t[..., None] * ab).norm(dim=-1)


def chamfer_loss(positions: torch.Tensor, dists: MaskDistances, edges: torch.Tensor, camera: Camera,
                 huber_delta: float, first_frame: int = 0,
                 cover: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """(L_outside, L_cover) of simulated frames first_frame..first_frame+F-1 (positions (F, V, 3)); edges
    (B, 2) long; cover=False: L_cover is not computed (0)."""
    uv, _ = project(positions, camera)                              # (F, V, 2) pixels
    frames = slice(first_frame, first_frame + positions.shape[0])
    dist = dists.outside[frames].to(positions.device)
    H, W = dist.shape[-2:]
    grid = torch.stack([uv[..., 0] / (W - 1) * 2 - 1, uv[..., 1] / (H - 1) * 2 - 1], dim=-1)
    d_out = F.grid_sample(dist, grid[:, None].to(dist.dtype), mode="bilinear", padding_mode="border",
                          align_corners=True)[:, 0, 0].to(positions.dtype)          # (F, V)
    d = huber_delta / dists.scale
    outside = _huber(d_out / dists.scale, d).mean()
    covers = []
    for k, c in enumerate(dists.contour[frames] if cover else []):
        if len(c) == 0:
            continue
        seg = point_segment_distance(c.to(uv), uv[k, edges[:, 0]], uv[k, edges[:, 1]]).min(dim=1).values
        covers.append(_huber(seg / dists.scale, d))
    coverage = torch.cat(covers).mean() if covers else positions.sum() * 0.0
    return outside, coverage


__all__ = ["MaskDistances", "mask_distances", "boundary_edges", "chamfer_loss", "point_segment_distance"]
