"""Whether a clip starts in motion, from its silhouettes alone (used by the shape phase's track and light
gates, saft.reconstruct.tracks / .light, and by phase 3's normal correction, saft.appearance.fit)."""

from __future__ import annotations

import numpy as np

# starts_moving's threshold: the silhouette's first change / its median change is 0.03 on the five appearance
# clips that start at rest, 0.08 on the demo, 0.73 on the same clips cut at frame 24 (BENCHMARKS.md).
START_SHARE = 0.3


def starts_moving(mask: np.ndarray, share: float = START_SHARE) -> bool:
    """Whether a clip (mask (N, H, W) in [0, 1]) starts in motion: the silhouette's change from frame 0 to 1
    (summed |Δmask|) is at least `share` times its median change between consecutive frames. Unlike the
    tracks' first step it does not depend on the texture."""
    if mask.shape[0] < 2:
        return False
    change = np.abs(np.diff(mask.astype(np.float64), axis=0)).sum(axis=(1, 2))
    return bool(change[0] >= share * np.median(change) and change[0] > 0)


__all__ = ["START_SHARE", "starts_moving"]
