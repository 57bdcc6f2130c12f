"""Which frames may teach the detail share: a frame whose motion is off by a fraction of a thread is left out.

``GuidedMaps`` blurs the phase-1 texture T inside each colour cluster (T_s: the texture's pixel noise
averaged away) and gives back a learnt share a_k of the removed detail D = T − T_s per cluster. Learnt from
every frame, a_k falls wherever the motion of later frames is off by a fraction of a thread: a weave that
does not line up across frames looks like noise, and the fit drops it (issue 28, BENCHMARKS.md "Why plaid
loses with saft's motion").

Here the frames are tested before the fit, without trusting their motion beyond what the test itself
checks. Each frame f is sampled into texture space through its mesh (``project_to_texture``: every texel's
point on the surface, projected into the image, visible texels only), high-passed inside the same clusters
(D_f) and brought to frame 0's shading. The share of the texture's detail that the frame repeats is

    R_f = Σ D · D_f / Σ D · D_0        (over the texels seen in both frames; R_0 = 1)

Frame 0's own detail D_0 shares the pattern AND the noise with D (the texture was fitted to frame 0); a
later frame shares only the pattern, and only where its motion lines the pattern up. Normalising by D_0
rather than by Σ D² cancels the amplitude that the texture fit gives the detail (it deconvolves the
pixels' footprint: D is about 3× stronger than the detail it explains in a frame). On the benchmark, R_f
stays within 0.7–1 of the first frames' R on the true motion of every fabric and on saft's motion of the
print, and falls to a quarter on saft's motion of the plaid after frame 10 (the weave no longer lines up).

``untrusted_detail_frames``: the frames whose R_f is below ``trust`` × the mean R of frames 1–2 (the
cloth has hardly moved there, and saft's shape error is smallest). The fit then takes the detail share's
gradient from the other frames only; every other parameter still learns from every frame. Where the first
frames repeat less than ``FLOOR`` of the detail (plain cotton, satin: the detail is the texture's pixel
noise, R ≈ 0), the test says nothing and every frame is kept.
"""

from __future__ import annotations

import numpy as np

from saft.appearance.guided import smooth_within_clusters
from saft.appearance.params import srgb_to_linear
from saft.io_utils import bilinear_sample
from saft.scene.camera import Camera


def texel_triangles(triangles, uvs, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(size, size) int64 index of the UV triangle holding each texel centre (−1: none) and (size, size, 3)
    its barycentric coordinates. uvs (V, 2) OBJ convention (row 0 of the texture = v 1)."""
    uv = np.asarray(uvs, dtype=np.float64)
    pix = np.stack([uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5], -1)  # (col, row)
    tri_of = np.full((size, size), -1, dtype=np.int64)
    bary = np.zeros((size, size, 3))
    for t, tri in enumerate(np.asarray(triangles)):
        p = pix[tri]
        lo = np.maximum(np.floor(p.min(0)).astype(int), 0)
        hi = np.minimum(np.ceil(p.max(0)).astype(int), size - 1)
        if (hi < lo).any():
            continue
        cc, rr = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        (x0, y0), (x1, y1), (x2, y2) = p
        den = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(den) < 1e-12:
            continue
        a = ((y1 - y2) * (cc - x2) + (x2 - x1) * (rr - y2)) / den
        b = ((y2 - y0) * (cc - x2) + (x0 - x2) * (rr - y2)) / den
        inside = (a >= -1e-6) & (b >= -1e-6) & (a + b <= 1 + 1e-6)
        tri_of[rr[inside], cc[inside]] = t
        bary[rr[inside], cc[inside]] = np.stack([a[inside], b[inside], 1.0 - a[inside] - b[inside]], -1)
    return tri_of, bary


def project_to_texture(vertices, triangles, tri_of: np.ndarray, bary: np.ndarray, camera: Camera,
                       image: np.ndarray, mask: np.ndarray, depth_tol: float = 0.005,
                       min_mask: float = 0.99) -> tuple[np.ndarray, np.ndarray]:
    """A frame sampled in texture space: (S, S, C) the image (bilinear) at each texel's point on the surface
    of `vertices` (V, 3), and (S, S) bool where that point is seen. Seen: inside the UV layout, projected
    inside the image's mask (≥ min_mask: not on the silhouette), and not behind another part of the cloth
    (its depth within depth_tol × depth of the nearest texel that lands in the same cell: a z-buffer of
    the texels themselves, on cells of s×s pixels with s chosen so that there are about two texels per
    cell where texels are larger than pixels)."""
    S = tri_of.shape[0]
    inside = tri_of >= 0
    tri = np.asarray(triangles)[tri_of[inside]]
    points = (np.asarray(vertices, dtype=np.float64)[tri] * bary[inside][..., None]).sum(1)
    px, z = camera.project(points)
    H, W = image.shape[:2]
    corners, _ = camera.project(np.asarray(vertices, dtype=np.float64))
    a, b, c = (corners[np.asarray(triangles)[:, i]] for i in range(3))
    area = 0.5 * np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]).sum()   # pixels
    cell = max(1, int(np.ceil(np.sqrt(2.0 * area / max(len(points), 1)))))
    col, row = np.round(px[:, 0]).astype(np.int64), np.round(px[:, 1]).astype(np.int64)
    on = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    Wc = (W + cell - 1) // cell
    key = (row // cell) * Wc + col // cell
    zbuf = np.full(((H + cell - 1) // cell) * Wc, np.inf)
    np.minimum.at(zbuf, key[on], z[on])
    seen = on.copy()
    seen[on] = z[on] <= zbuf[key[on]] * (1.0 + depth_tol)
    seen &= bilinear_sample(np.asarray(mask, dtype=np.float64), px) >= min_mask
    values = np.zeros((S, S, image.shape[2]))
    values[inside] = bilinear_sample(np.asarray(image, dtype=np.float64), px)
    valid = np.zeros((S, S), bool)
    valid[inside] = seen
    return values, valid


def frame_detail(values: np.ndarray, valid: np.ndarray, smooth: np.ndarray, labels: np.ndarray,
                 sigma: float) -> np.ndarray:
    """A projected frame's detail inside the clusters (its blur over seen texels only removed), brought to
    the texture's shading (× smooth / the frame's blur); 0 where not seen."""
    blur = smooth_within_clusters(values, labels, sigma, weight=valid)
    return np.where(valid[..., None], (values - blur) * smooth / np.maximum(blur, 1e-4), 0.0)


def detail_repeat_per_frame(model, vertices, triangles, uvs, camera: Camera, rgb_srgb, mask, sigma: float,
                            frames=None) -> np.ndarray:
    """(F,) for each frame f, R_f = Σ D·D_f / Σ D·D_0 over the texels seen in both (all clusters pooled):
    how much of the texture's detail that frame repeats (1 for frame 0; a weave on a well-aligned frame
    keeps most of it, the same weave on a frame whose motion is off by a fraction of a thread little).
    frames: the frames to evaluate (default all); the others are NaN."""
    smooth = model.texture.detach().cpu().numpy().astype(np.float64)
    detail = model.detail.detach().cpu().numpy().astype(np.float64)
    labels = model.members.argmax(0).cpu().numpy()
    tri_of, bary = texel_triangles(triangles, uvs, smooth.shape[0])

    def detail_of(f):
        linear = srgb_to_linear(np.clip(np.asarray(rgb_srgb[f], dtype=np.float64), 0.0, 1.0))
        values, valid = project_to_texture(vertices[f], triangles, tri_of, bary, camera, linear, mask[f])
        return frame_detail(values, valid, smooth, labels, sigma), valid

    d0, valid0 = detail_of(0)
    out = np.full(len(vertices), np.nan)
    out[0] = 1.0
    for f in (range(1, len(vertices)) if frames is None else frames):
        if f == 0:
            continue
        d, valid = detail_of(f)
        m = valid0 & valid
        c0 = float((detail[m] * d0[m]).sum())
        out[f] = float((detail[m] * d[m]).sum()) / c0 if c0 > 0 else 0.0
    return out


FLOOR = 0.1    # below this repeat on the first frames the detail is noise everywhere: no frame is judged


def detail_trust_test(model, vertices, triangles, uvs, camera: Camera, rgb_srgb, mask, sigma: float,
                      trust: float) -> tuple[float, list[int]]:
    """(ref, untrusted): ref the mean detail repeat R (detail_repeat_per_frame) of frames 1 and 2, untrusted
    the frames (sorted) whose R_f is below trust × ref; none when ref is below FLOOR (the rest of the frames
    are then not evaluated). The video has at least 3 frames."""
    args = (model, vertices, triangles, uvs, camera, rgb_srgb, mask, sigma)
    first = detail_repeat_per_frame(*args, frames=[1, 2])   # the reference first: the rest only if it counts
    ref = float(np.mean(first[1:3]))
    if ref < FLOOR:
        return ref, []
    R = detail_repeat_per_frame(*args, frames=range(3, len(vertices)))
    R[1:3] = first[1:3]
    return ref, [int(f) for f in np.flatnonzero(R < trust * ref)]


def untrusted_detail_frames(model, vertices, triangles, uvs, camera: Camera, rgb_srgb, mask, sigma: float,
                            trust: float) -> list[int]:
    """The frames (sorted) whose detail repeat R_f (detail_repeat_per_frame) is below trust × the mean R of
    frames 1 and 2; none when that reference is below FLOOR or the video has fewer than 3 frames."""
    if len(vertices) < 3 or trust <= 0:
        return []
    return detail_trust_test(model, vertices, triangles, uvs, camera, rgb_srgb, mask, sigma, trust)[1]
