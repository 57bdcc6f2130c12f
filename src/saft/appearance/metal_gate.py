"""Which clusters may be metal (``appearance.metal_gate``): the colour of their highlights (issue 28).

A dielectric's highlight has the light's colour, a metal's the colour of its F0, which is also the colour
the metal shows everywhere else (its whole radiance is specular). So a cluster whose highlights over the
frames are coloured like its own texture may be metal; one whose highlights shift its colour towards the
light's (the satin's white streak on red) shows a dielectric's highlight and keeps the default treatment
(no metal colour, the sparsity prior). The frames are sampled into texture space through their meshes
(appearance.frame_specular.FrameStack) on a grid of GATE_GRID texels.
"""

from __future__ import annotations

import warnings

import numpy as np

from saft.appearance.frame_specular import FrameStack

# the texel grid of the gate's frames: the lamé's threads are 3/128 of the cloth wide, 3 texels at 128 (the
# benchmark's 320x240 cloth spans about 150 pixels: about one pixel per texel)
GATE_GRID = 128
GATE_FRAMES = 32        # frames sampled (evenly spaced, frame 0 among them)
CLIPPED = 0.95          # linear radiance of a channel at which a sample counts as clipped (sRGB 0.98)
MIN_SEEN = 3            # frames a texel must be seen in to count
MIN_PEAK = 1.5          # how many times its median the brightest frame must be to be a highlight


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """(…, 3) rgb / (r + g + b): the colour without its brightness."""
    rgb = np.maximum(np.asarray(rgb, dtype=np.float64), 0.0)
    return rgb / np.maximum(rgb.sum(-1, keepdims=True), 1e-9)


def _highlights(radiance: np.ndarray, seen: np.ndarray, min_seen: int, min_peak: float):
    """Per texel: the brightest frame's excess over the per-channel median of its frames (G, G, 3), that
    median (G, G, 3), and the excess's brightness where it counts as a highlight (seen in at least min_seen
    frames, at least min_peak times as bright as the median), else 0 (G, G)."""
    radiance = np.asarray(radiance, dtype=np.float64)
    seen = seen & (radiance.max(-1) < CLIPPED)   # a clipped highlight is white whatever its colour
    rad = np.where(seen[..., None], radiance, np.nan)
    counted = seen.sum(0) >= min_seen
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # texels no frame sees
        med = np.nanmedian(rad, axis=0)                                              # (G, G, 3)
        lum = np.where(seen, np.nansum(rad, -1), -np.inf)                            # (F, G, G)
    top = np.take_along_axis(np.nan_to_num(rad), lum.argmax(0)[None, ..., None], 0)[0]
    med = np.nan_to_num(med)
    excess = np.maximum(top - med, 0.0)
    peak = top.sum(-1) / np.maximum(med.sum(-1), 1e-9)
    return excess, med, excess.sum(-1) * (counted & (peak >= min_peak))


def highlight_colour(radiance: np.ndarray, seen: np.ndarray, labels: np.ndarray, k: int, min_seen: int = MIN_SEEN,
                     min_peak: float = MIN_PEAK) -> np.ndarray:
    """(K,) per cluster, how much its highlights keep its own colour: 1 a metal's, 0 a dielectric's under grey
    light, NaN where nothing tells (no highlight, or a grey cluster).

    radiance (F, G, G, 3) linear, seen (F, G, G) bool: the frames in texture space (frame_specular.FrameStack);
    labels (G, G) the texels' clusters. At each texel seen in at least min_seen frames, the brightest frame's
    excess over the per-channel median of its frames is a highlight where it is at least min_peak times as
    bright as the median. A Lambertian texel brighter by its shading adds its own colour (no highlight by
    this test unless its shading changes that much, and then a colour shift of 0, like a metal); a
    dielectric's highlight adds the light's colour, a metal's its F0's. Per texel the shift |chroma(excess) −
    chroma(median)| is compared with the median's own colourfulness |chroma(median) − grey|; the cluster's
    score is 1 − Σ w·shift / Σ w·colourfulness, w the excess's brightness."""
    return _colour_scores(*_highlights(radiance, seen, min_seen, min_peak), labels, k)


def _colour_scores(excess: np.ndarray, med: np.ndarray, w: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    grey = np.full(3, 1 / 3)
    shift = np.linalg.norm(chromaticity(excess) - chromaticity(med), axis=-1)
    colourful = np.linalg.norm(chromaticity(med) - grey, axis=-1)
    score = np.full(k, np.nan)
    for c in range(k):
        wc = w * (labels == c)
        if wc.sum() <= 0 or (wc * colourful).sum() / wc.sum() < 0.05:   # no highlight, or a grey cluster
            continue
        score[c] = 1.0 - (wc * shift).sum() / (wc * colourful).sum()
    return score


def highlight_hue(radiance: np.ndarray, seen: np.ndarray, labels: np.ndarray, k: int, min_seen: int = MIN_SEEN,
                  min_peak: float = MIN_PEAK) -> np.ndarray:
    """(K, 3) per cluster, the colour of its highlights (highlight_colour's excesses): their chromaticity
    weighted by their brightness, over its brightest channel (a metal's F0 up to its brightness: its highlight
    is F0 times the light's change, which is grey on the whole); NaN rows where the cluster has none."""
    excess, _, w = _highlights(radiance, seen, min_seen, min_peak)
    return _hues(excess, w, labels, k)


def _hues(excess: np.ndarray, w: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    chroma = chromaticity(excess)
    hue = np.full((k, 3), np.nan)
    for c in range(k):
        wc = w * (labels == c)
        if wc.sum() > 0:
            mean = (wc[..., None] * chroma).sum((0, 1)) / wc.sum()
            hue[c] = mean / max(mean.max(), 1e-9)
    return hue


def metal_scores(model, vertices, triangles, uvs, camera, rgb_srgb, mask, grid: int = GATE_GRID,
                 frames: int = GATE_FRAMES):
    """A GuidedMaps model's clusters from the video: ((K,) highlight_colour, NaN where nothing tells;
    (K, 3) highlight_hue, NaN rows where a cluster has no highlight), from one pass over the highlights."""
    n = len(vertices)
    picked = np.linspace(0, n - 1, min(frames, n)).round().astype(int)
    stack = FrameStack(vertices, triangles, uvs, camera, rgb_srgb, mask, grid, (4, 8), picked)
    members = model.members.cpu().numpy()
    idx = ((np.arange(grid) + 0.5) * members.shape[-1] / grid).astype(int)
    labels = members.argmax(0)[np.ix_(idx, idx)]
    radiance, seen = stack.radiance.numpy(), stack.seen.numpy()
    excess, med, w = _highlights(radiance, seen, MIN_SEEN, MIN_PEAK)
    return _colour_scores(excess, med, w, labels, model.num_clusters), _hues(excess, w, labels, model.num_clusters)
