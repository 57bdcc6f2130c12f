"""Point tracks of the template's vertices through the video, and the track loss of the shape phase.

The image loss alone pulls a simulated frame only as far as the printed pattern's period: a frame that
starts off by more settles a period away, and every later frame inherits the error through the
simulation. Point tracks give each visible vertex a 2D target in every frame that does not depend on
the print registering under the fixed texture, on the lighting, or on how far the simulation is off.

Tracks come from classical dense optical flow (OpenCV's DIS, no learned weights, nothing downloaded):
every vertex visible in frame 0 starts at its projection and is carried from frame to frame by the
forward flow. A track ends for good at the first frame where the backward flow does not bring it back
(forward–backward check: occlusion, a fold, flow leaving the cloth) or where it leaves the cloth's mask.

Chained flow accumulates error (about a pixel over 30 frames, more where the cloth folds), and a
drifted track pulls the simulation towards a stretched cloth. So each frame is also matched directly
to frame 0 (re-anchoring): where the direct flow of the track's start passes its own forward–backward
check and lands within `reanchor_radius` pixels of the chained position, the track takes the direct
position, which carries no accumulated drift, and chaining goes on from there.

A part of the cloth that folds over another carries its texture across the points below it, and the
flow there is smooth: a track of a covered point can follow the flap and still pass the forward–backward
check (on the fold benchmark scene, 41 tracks 10–19 px off by the last frame). What does change is the
colour under the track: a tracked point keeps its colour from frame to frame up to shading and noise,
while a track that jumps onto the flap lands on another part of the print. So a track also ends at the
first step whose colour change (3 × 3 box-filtered RGB, largest channel) exceeds `jump_ratio` times the
video's median step over all tracks (its noise and shading level; never below `jump_floor`).

A track can also slide slowly (a curling edge, a cloth turning at a fast swing): no single step jumps, but
its point drifts onto other threads of the print. Shading changes a point's brightness, not its
chromaticity (rgb / (r + g + b), under a white light), so a track also ends at the first frame where the
chromaticity under it (5 × 5 box-filtered) differs from its frame-0 chromaticity by more than `drift` in
some channel. On the independent-simulator scenes the track-frames that pass 0.02 are 0.1-0.3 px off
(median), those beyond it 3-8 px (BENCHMARKS.md, "Why saft loses the independent scenes"). A print
without colour never triggers it. Instead of that cut, shape.track_drift_scale weighs each track-frame by
exp(−(d / scale)²), d the largest drift so far (drift_confidence; off by default: it helps the
independent-simulator scenes and costs R1, BENCHMARKS.md).

Flow is only as good as the texture it follows: on a plain fabric (a matte cotton, a smooth satin) DIS
follows the shading and the moving highlights, and the tracks of a clip that starts in motion end up several
pixels off (BENCHMARKS.md, "A flat rest shape for clips that start curved"). Shi and Tomasi's measure of how
well a point can be tracked is the smaller eigenvalue λ_min of the structure tensor (the summed outer
products of the image gradient) in a window around it; it is small where the image varies in one direction
or none. texture_strength gives it for each track's start, in units of the video's noise: λ_min of frame
0's luma (Gaussian σ = 1.5 px, a 15 × 15 window) divided by σ², σ the noise level of frame 0 inside the
mask (Immerkær's estimator). Within one clip it hardly tells good tracks from bad (on the curved satin the
strongest quarter is as often > 3 px off as the weakest, a moving highlight's edge being strong texture),
but between clips it does: the median over a clip's tracks is 0.02 on the plain cotton, 0.12 on the satin,
1.1–1.8 on the printed Newton scenes, 27 on R1. So with shape.track_texture = Q0 > 0 the whole track loss
weighs min(1, Q / Q0), Q that median (texture_confidence): the tracks of a plain fabric weigh little, those
of a printed cloth are unchanged. Only where the clip starts curved in motion (saft.scene.motion.
starts_curved_in_motion: the silhouette changes from frame 0 to 1 and the template is clearly billowed, as on
the appearance clips cut at frame 24): from rest the flow's first steps are small, and weighing the same
plain fabrics' tracks down there helped as often as it hurt (BENCHMARKS.md, "Track confidence on clips that
start moving"); on a flat cloth already in a breeze (Newton's appearance clips) the tracks are 0.3–1.4 px
off (median) and weighing them down cost 2–3× (BENCHMARKS.md, "Fourteenth session").

    L_track = mean over valid (frame, vertex) of huber(|π(x_v,t) − p_v,t| / s)

π: the working camera's projection, p: the track, s: the image's larger side in pixels (so the loss is
in fractions of the image and does not change with the working resolution).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import uniform_filter

from saft.io_utils import bilinear_sample
from saft.scene.camera import Camera

log = logging.getLogger("saft")


@dataclass
class VertexTracks:
    points: torch.Tensor    # (N, V, 2) pixel coordinates (u = column, v = row) in the working image
    valid: torch.Tensor     # (N, V) bool: the track is trusted in that frame
    scale: float            # pixels per unit of the loss (the image's larger side)
    weight: torch.Tensor | None = None   # (N, V) confidence of each track-frame in the loss (None = all 1)
    strength: float = 1.0   # absolute weight of the whole loss in [0, 1] (texture_confidence), not normalised

    def coverage(self) -> np.ndarray:
        """(N,) fraction of the vertices with a valid track in each frame."""
        return self.valid.float().mean(dim=1).cpu().numpy()


def to_gray_u8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float sRGB in [0, 1] → (H, W) uint8 luma (Rec. 601 weights)."""
    gray = rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114
    return np.clip(gray * 255.0 + 0.5, 0, 255).astype(np.uint8)


def dense_flow(gray0: np.ndarray, gray1: np.ndarray) -> np.ndarray:
    """(H, W, 2) optical flow from gray0 to gray1 (OpenCV DIS, 'medium' preset), float32 pixels."""
    import cv2  # opencv-python-headless; imported here so that saft imports without cv2's start-up cost

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(gray0, gray1, None)


def _flow_step(flow_fwd: np.ndarray, flow_bwd: np.ndarray, mask: np.ndarray, src: np.ndarray,
               fb_threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Move points `src` (P, 2) by a forward flow; ok where the backward flow brings them back within
    fb_threshold pixels and they land inside the image on the mask."""
    H, W = mask.shape
    p = src + bilinear_sample(flow_fwd, src)
    back = p + bilinear_sample(flow_bwd, p)
    ok = np.linalg.norm(back - src, axis=1) <= fb_threshold
    inside = (p[:, 0] >= 0) & (p[:, 0] <= W - 1) & (p[:, 1] >= 0) & (p[:, 1] <= H - 1)
    return p, ok & inside & (bilinear_sample(mask, p) >= 0.5)


def track_points(rgb: np.ndarray, mask: np.ndarray, start: np.ndarray, start_valid: np.ndarray,
                 fb_threshold: float = 1.0, reanchor_radius: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Carry points from frame 0 through the video by chained forward flow, re-anchored to frame 0.

    rgb (N, H, W, 3) float sRGB, mask (N, H, W) in [0, 1], start (P, 2) pixel positions in frame 0,
    start_valid (P,) bool. Returns points (N, P, 2) and valid (N, P): a point stays valid while the
    backward flow returns it within `fb_threshold` pixels and it stays on the mask.
    reanchor_radius > 0: where the direct flow from frame 0 passes the same checks and lands within this
    many pixels of the chained point, the point takes the direct position (0 = chained flow only).
    """
    n = rgb.shape[0]
    points = np.zeros((n, len(start), 2), dtype=np.float64)
    valid = np.zeros((n, len(start)), dtype=bool)
    points[0], valid[0] = start, start_valid
    gray0 = gray_prev = to_gray_u8(rgb[0])
    for t in range(1, n):
        gray = to_gray_u8(rgb[t])
        p, ok = _flow_step(dense_flow(gray_prev, gray), dense_flow(gray, gray_prev), mask[t], points[t - 1],
                           fb_threshold)
        ok &= valid[t - 1]
        if reanchor_radius > 0 and t > 1:
            q, q_ok = _flow_step(dense_flow(gray0, gray), dense_flow(gray, gray0), mask[t], start, fb_threshold)
            snap = ok & q_ok & (np.linalg.norm(q - p, axis=1) <= reanchor_radius)
            p = np.where(snap[:, None], q, p)
        points[t] = np.where(ok[:, None], p, points[t - 1])
        valid[t] = ok
        gray_prev = gray
    return points, valid


def track_colours(rgb: np.ndarray, points: np.ndarray, box: int) -> np.ndarray:
    """(N, P, 3) colour under each track: every frame box × box box-filtered, sampled bilinearly at the
    track's position. rgb (N, H, W, 3), points (N, P, 2)."""
    return np.stack([bilinear_sample(uniform_filter(frame, size=(box, box, 1), mode="nearest"), pts)
                     for frame, pts in zip(rgb, points)])


def appearance_steps(rgb: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, P) colour change along each track: the largest channel of |c_t(p_t) − c_{t−1}(p_{t−1})|, c the
    3 × 3 box-filtered frame sampled at the track's position; 0 in frame 0. rgb (N, H, W, 3), points (N, P, 2)."""
    colours = track_colours(rgb, points, box=3)
    steps = np.zeros(points.shape[:2])
    steps[1:] = np.abs(np.diff(colours, axis=0)).max(axis=-1)
    return steps


def end_at_appearance_jumps(rgb: np.ndarray, points: np.ndarray, valid: np.ndarray, jump_ratio: float,
                            jump_floor: float) -> np.ndarray:
    """`valid` with every track ended from its first step whose colour change (appearance_steps) exceeds
    max(jump_floor, jump_ratio × the median step over all valid steps); jump_ratio 0 changes nothing."""
    if jump_ratio <= 0 or points.shape[0] < 2:
        return valid
    steps = appearance_steps(rgb, points)
    moving = valid[1:] & valid[:-1]
    if not moving.any():
        return valid
    threshold = max(jump_floor, jump_ratio * float(np.median(steps[1:][moving])))
    jumped = np.zeros_like(valid)
    jumped[1:] = moving & (steps[1:] > threshold)
    return valid & ~np.maximum.accumulate(jumped, axis=0)


def colour_drift(rgb: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, P) the largest drift so far of the chromaticity (5 × 5 box-filtered rgb divided by r + g + b)
    under each track from its frame-0 one (largest channel), running maximum over the frames."""
    colours = track_colours(rgb, points, box=5)
    chroma = colours / np.clip(colours.sum(axis=-1, keepdims=True), 1e-3, None)
    return np.maximum.accumulate(np.abs(chroma - chroma[:1]).max(axis=-1), axis=0)


def end_at_colour_drift(rgb: np.ndarray, points: np.ndarray, valid: np.ndarray, drift: float) -> np.ndarray:
    """`valid` with every track ended from its first frame whose chromaticity differs from its frame-0 one
    by more than `drift` in some channel (colour_drift); 0 changes nothing."""
    if drift <= 0 or points.shape[0] < 2:
        return valid
    return valid & ~(colour_drift(rgb, points) > drift)


def drift_confidence(rgb: np.ndarray, points: np.ndarray, scale: float) -> np.ndarray | None:
    """(N, P) weight exp(−(d / scale)²) of each track-frame, d its colour_drift so far; None for scale 0."""
    if scale <= 0:
        return None
    return np.exp(-(colour_drift(rgb, points) / scale) ** 2)


def noise_level(gray: np.ndarray, mask: np.ndarray) -> float:
    """Standard deviation of the noise of a gray image (H, W) inside mask (H, W) >= 0.5, by Immerkær's
    estimator (1996): the mean absolute response of the Laplacian difference [[1, -2, 1], [-2, 4, -2],
    [1, -2, 1]] times sqrt(π / 2) / 6, over the mask eroded by 2 pixels (the cloth's outline is no noise)."""
    import cv2  # opencv-python-headless, as dense_flow

    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float64)
    response = np.abs(cv2.filter2D(gray.astype(np.float64), -1, kernel, borderType=cv2.BORDER_REFLECT))
    inside = cv2.erode((mask >= 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if not inside.any():
        return 0.0
    return float(np.sqrt(np.pi / 2) / 6 * response[inside].mean())


def texture_strength(rgb0: np.ndarray, mask0: np.ndarray, points: np.ndarray, blur: float = 1.5,
                     window: int = 15, noise_floor: float = 0.5) -> np.ndarray:
    """(P,) Shi–Tomasi texture strength at pixel positions `points` (P, 2) of frame 0 (rgb0 (H, W, 3) sRGB,
    mask0 (H, W)): the smaller eigenvalue of the structure tensor of the 0–255 luma blurred by a Gaussian of
    σ = `blur` px, summed over a `window` × `window` box (Sobel 3 × 3 gradients, cv2.cornerMinEigenVal),
    divided by the square of frame 0's noise level (noise_level, never below `noise_floor` gray levels)."""
    import cv2

    gray = to_gray_u8(rgb0).astype(np.float32)
    lam = cv2.cornerMinEigenVal(cv2.GaussianBlur(gray, (0, 0), blur), window, 3)
    sigma = max(noise_level(gray, mask0), noise_floor)
    return bilinear_sample(lam, points) / sigma ** 2


def texture_q(rgb0: np.ndarray, mask0: np.ndarray, points: np.ndarray, valid: np.ndarray) -> float:
    """Q of a clip: the median texture_strength at the points that start a track (points (P, 2), valid (P,)
    bool); inf where none does."""
    if not valid.any():
        return float("inf")
    return float(np.median(texture_strength(rgb0, mask0, points[valid])))


def texture_confidence(rgb0: np.ndarray, mask0: np.ndarray, points: np.ndarray, valid: np.ndarray,
                       q0: float) -> float:
    """Weight min(1, Q / q0) of a clip's track loss (Q: texture_q); 1 for q0 = 0 or no track."""
    if q0 <= 0 or not valid.any():
        return 1.0
    return min(1.0, texture_q(rgb0, mask0, points, valid) / q0)


def project(points: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (..., 3) → pixel coordinates (..., 2) in `camera`'s image and camera depth (...)."""
    R = torch.as_tensor(camera.world_to_camera[:3, :3], dtype=points.dtype, device=points.device)
    t = torch.as_tensor(camera.world_to_camera[:3, 3], dtype=points.dtype, device=points.device)
    K = torch.as_tensor(camera.K, dtype=points.dtype, device=points.device)
    pc = points @ R.T + t
    z = pc[..., 2]
    xy = pc[..., :2] / z.clamp_min(1e-9).unsqueeze(-1)
    uv = xy @ K[:2, :2].T + K[:2, 2]
    return uv, z


def visible_vertices(template: torch.Tensor, camera: Camera, mask0: np.ndarray, depth0: np.ndarray,
                     depth_tolerance: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions (V, 2) of the template's vertices in frame 0 and which of them can start a track:
    inside the image, on the frame-0 mask, and not hidden by the cloth itself (rendered depth)."""
    uv, z = project(template.detach().to(torch.float64), camera)
    uv, z = uv.cpu().numpy(), z.cpu().numpy()
    H, W = mask0.shape
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    on_mask = bilinear_sample(mask0, uv) >= 0.5
    cols = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, W - 1)
    rows = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, H - 1)
    d = depth0[rows, cols]
    unoccluded = (d <= 0) | (z <= d + depth_tolerance)
    return uv, inside & on_mask & unoccluded


def compute_vertex_tracks(rgb: torch.Tensor, mask: torch.Tensor, template: torch.Tensor, camera: Camera,
                          depth0: torch.Tensor, fb_threshold: float, reanchor_radius: float = 0.0,
                          jump_ratio: float = 0.0, jump_floor: float = 0.03, drift: float = 0.0,
                          drift_scale: float = 0.0, texture: float = 0.0) -> VertexTracks:
    """Tracks of every template vertex through the target video (rgb (N, H, W, 3), mask (N, H, W)); with
    jump_ratio > 0 a track also ends at its first colour jump (end_at_appearance_jumps), with drift > 0 where
    its chromaticity drifts from frame 0's (end_at_colour_drift); with drift_scale > 0 each track-frame is
    weighted by drift_confidence; with texture > 0 the whole loss by texture_confidence (the caller,
    saft.reconstruct.shape_phase.shape_tracks, passes it only where the clip starts curved in motion)."""
    rgb_np = rgb.detach().cpu().numpy()
    mask_np = mask.detach().cpu().numpy()
    start, ok = visible_vertices(template, camera, mask_np[0], depth0.detach().cpu().numpy())
    pts, valid = track_points(rgb_np, mask_np, start, ok, fb_threshold, reanchor_radius)
    valid = end_at_appearance_jumps(rgb_np, pts, valid, jump_ratio, jump_floor)
    valid = end_at_colour_drift(rgb_np, pts, valid, drift)
    weight = drift_confidence(rgb_np, pts, drift_scale)
    strength = texture_confidence(rgb_np[0], mask_np[0], start, ok, texture) if texture > 0 else 1.0
    if strength < 1.0:
        log.info("point tracks on weak texture: the track loss weighs %.3g (shape.track_texture)", strength)

    def tensor(a: np.ndarray | None) -> torch.Tensor | None:
        return None if a is None else torch.as_tensor(a, dtype=template.dtype, device=template.device)

    return VertexTracks(points=tensor(pts), valid=torch.as_tensor(valid, device=template.device),
                        scale=float(max(camera.width, camera.height)), weight=tensor(weight),
                        strength=strength)


def hidden_vertices(positions: torch.Tensor, depths: Sequence[torch.Tensor], camera: Camera,
                    tolerance: float) -> torch.Tensor:
    """(F, V) bool: the vertex lies more than `tolerance` behind the rendered surface at its pixel, i.e. the
    current reconstruction hides it behind another part of the cloth (positions (F, V, 3); depths: per frame
    the rendered camera depth (H, W) or (1, H, W), 0 where nothing is drawn). Only the V pixels under the
    vertices are read (gathering before any copy: converting R1's full depth maps cost 3.5 % of its run)."""
    with torch.no_grad():
        uv, z = project(positions.detach(), camera)
        H, W = depths[0].shape[-2:]
        cols = uv[..., 0].round().long().clamp(0, W - 1)
        rows = uv[..., 1].round().long().clamp(0, H - 1)
        index = rows * W + cols
        d = torch.stack([depth.reshape(-1)[i] for depth, i in zip(depths, index)]).to(z.dtype)
        return (d > 0) & (z > d + tolerance)


def track_loss(positions: torch.Tensor, tracks: VertexTracks, camera: Camera, huber_delta: float,
               first_frame: int = 0, hidden: torch.Tensor | None = None) -> torch.Tensor:
    """L_track of simulated frames first_frame..first_frame+F-1 (positions (F, V, 3)); zero when no track
    is valid there; with tracks.weight, the weighted mean over the valid track-frames; with
    tracks.strength, times it.

    huber_delta in pixels: residuals beyond it count linearly (a track that went astray pulls less).
    hidden (F, V) bool: vertices the reconstruction itself hides (hidden_vertices); their tracks are
    skipped in these frames (a track that survived the flow's checks through a fold is wrong there)."""
    frames = slice(first_frame, first_frame + positions.shape[0])
    valid = tracks.valid[frames]
    if hidden is not None:
        valid = valid & ~hidden.to(valid.device)
    if not bool(valid.any()):
        return positions.sum() * 0.0
    uv, _ = project(positions, camera)
    r = (uv - tracks.points[frames].to(uv)).norm(dim=-1) / tracks.scale
    d = huber_delta / tracks.scale
    h = torch.where(r <= d, 0.5 * r * r, d * (r - 0.5 * d))
    if tracks.strength != 1.0:
        h = h * tracks.strength
    if tracks.weight is None:
        return h[valid].mean()
    w = tracks.weight[frames].to(h)[valid]
    return (h[valid] * w).sum() / w.sum().clamp_min(1e-12)


__all__ = ["VertexTracks", "compute_vertex_tracks", "end_at_colour_drift", "texture_strength", "texture_q", "texture_confidence",
           "noise_level", "track_loss", "hidden_vertices", "track_points", "project", "visible_vertices",
           "dense_flow", "bilinear_sample", "to_gray_u8"]
