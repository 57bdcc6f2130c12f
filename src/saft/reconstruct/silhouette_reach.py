"""A silhouette term whose pull grows with the gap to the observed mask's border (issue 29; not in the paper).

The silhouette term (saft.reconstruct.losses.silhouette_loss, the coverage MSE) has a gradient only at the
rendered silhouette's pixels (the renderer's analytic antialiasing), and there its size does not depend on
how far the observed mask reaches beyond: a rendered edge 15 px inside the mask is pulled no harder than one
1 px inside. On R1 the image-left edge strip of frames 40-49 ends 10-20 px inside the mask on every row of
the lower half (BENCHMARKS.md, "R1's border depth"), held there by the other terms.

With shape.sil_reach_px = r > 0, in a scene with pinned vertices (reach_px), every pixel of the mask weighs

    w = 1 + sil_reach_gain · (min(d, r) / r)²

in the coverage MSE, d its distance in pixels to the nearest pixel off the (binarised) mask; pixels off the
mask weigh 1. The gradient still lives only on the rendered silhouette; where that silhouette borders mask
pixels the render leaves uncovered, d is the gap to the mask's border, and the pull grows with it (the
square keeps the usual gap of a pixel or two at weight ~1). Where the render covers the mask (also a fold's
crease with cloth on both sides) the residual, and with it the weight's effect, is 0; the render's spills
beyond the mask weigh 1, as before: the term only pulls an edge out to the mask, never in. At the mask's
border w ~ 1 on both sides, so the coverage's optimum does not move.

The distances are computed once per video (scipy's exact Euclidean transform, capped at r, kept as uint8)
and memoised by the target tensor's identity (saft.render.topology.TensorCache).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from saft.render.topology import TensorCache

_DISTANCES = TensorCache()   # by the target mask's identity and the reach: its capped distances


def inside_distance(mask: np.ndarray, cap: float) -> np.ndarray:
    """(H, W) distance in pixels of each pixel of the mask (> 0.5) to the nearest pixel off it, capped at
    `cap`; 0 off the mask. A mask that fills the whole image counts the image's outside as off it."""
    inside = np.pad(np.asarray(mask) > 0.5, 1, constant_values=False)
    d = distance_transform_edt(inside)[1:-1, 1:-1]
    return np.minimum(d, cap)


def reach_distances(target_mask: torch.Tensor, reach_px: float) -> torch.Tensor:
    """(N, H, W) uint8 capped inside distances of every frame's mask, on the mask's device; memoised."""
    hit = _DISTANCES.get(target_mask, reach_px)
    if hit is not None:
        return hit
    cap = min(float(reach_px), 255.0)
    masks = target_mask.detach().cpu().numpy()
    d = np.stack([np.rint(inside_distance(m, cap)) for m in masks]).astype(np.uint8)
    return _DISTANCES.put(target_mask, torch.from_numpy(d).to(target_mask.device), reach_px)


def reach_weights(distances: torch.Tensor, reach_px: float, gain: float, dtype=torch.float32) -> torch.Tensor:
    """Per-pixel weights 1 + gain · (min(d, r) / r)² of uint8 distances (already capped at r)."""
    s = distances.to(dtype) / float(reach_px)
    return 1.0 + gain * s.clamp(max=1.0) ** 2


def reach_px(cfg, pinned) -> float:
    """The run's reach: shape.sil_reach_px where the scene pins vertices, 0 (off) where nothing does
    (`pinned`: the simulator's pinned indices or None). Without pins nothing holds the cloth's depth, and a
    pull on the silhouette is met by moving the cloth towards the camera (perspective makes it project
    larger) instead of widening it: R1's left strip 3-5 mm nearer in every frame (BENCHMARKS.md, "A
    silhouette pull with reach at the border")."""
    return 0.0 if pinned is None or len(pinned) == 0 else cfg.sil_reach_px


def silhouette_weights(target_mask: torch.Tensor, lo: int, hi: int, reach_px: float,
                       gain: float) -> torch.Tensor | None:
    """The weights of frames lo..hi-1 (hi - lo, H, W), or None when the option is off (reach_px <= 0 or
    gain <= 0): the plain coverage MSE."""
    if reach_px <= 0 or gain <= 0:
        return None
    return reach_weights(reach_distances(target_mask, reach_px)[lo:hi], reach_px, gain, target_mask.dtype)


__all__ = ["inside_distance", "reach_distances", "reach_px", "reach_weights", "silhouette_weights"]
