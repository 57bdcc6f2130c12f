"""Whether a clip starts in motion, from its silhouettes alone, and whether its template starts curved (used
by the shape phase's track and light gates, saft.reconstruct.tracks / .light, and by phase 3's normal
correction, saft.appearance.fit)."""

from __future__ import annotations

import numpy as np

from saft.scene.mesh import vertex_normals

# starts_moving's threshold: the silhouette's first change / its median change is 0.03 on the five appearance
# clips that start at rest, 0.08 on the demo, 0.73 on the same clips cut at frame 24, 0.90 on Newton's
# appearance clips (a flat cloth already in a breeze; BENCHMARKS.md).
START_SHARE = 0.3
# starts_curved's threshold (bend_degrees of the template): 0 on the appearance clips that start at rest and
# on Newton's appearance clips, 16.8 on the clips cut at frame 24 (billowed); the real scenes R1–R6's
# templates 4.7–8.7 (BENCHMARKS.md, "Fourteenth session"). Between the two groups measured, above the real
# templates' range: only a clearly billowed frame 0 counts.
CURVED_DEGREES = 12.0


def starts_moving(mask: np.ndarray, share: float = START_SHARE) -> bool:
    """Whether a clip (mask (N, H, W) in [0, 1]) starts in motion: the silhouette's change from frame 0 to 1
    (summed |Δmask|) is at least `share` times its median change between consecutive frames. Unlike the
    tracks' first step it does not depend on the texture."""
    if mask.shape[0] < 2:
        return False
    change = np.array([np.abs(mask[t + 1].astype(np.float64) - mask[t]).sum() for t in range(mask.shape[0] - 1)])
    return bool(change[0] >= share * np.median(change) and change[0] > 0)


def bend_degrees(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """How far a mesh is from flat: the mean angle (degrees) between its vertex normals and their mean
    direction (0 for a plane)."""
    n = vertex_normals(vertices, triangles)
    mean = n.mean(axis=0)
    length = float(np.linalg.norm(mean))
    if length < 1e-12:
        return 90.0
    return float(np.degrees(np.arccos(np.clip(n @ (mean / length), -1.0, 1.0))).mean())


def starts_curved_in_motion(mask: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                            share: float = START_SHARE, degrees: float = CURVED_DEGREES) -> bool:
    """Whether a clip starts in motion (starts_moving) from a clearly curved frame 0 (its template's
    bend_degrees >= `degrees`): a cloth cut from the middle of its motion, whose frame-0 shading moves with
    the folds, not with the fabric. A flat cloth already in a breeze does not count."""
    return bend_degrees(vertices, triangles) >= degrees and starts_moving(mask, share)


__all__ = ["CURVED_DEGREES", "START_SHARE", "bend_degrees", "starts_curved_in_motion", "starts_moving"]
