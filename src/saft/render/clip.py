"""Camera → clip space for the rasterizers.

Clip space here is nvdiffrast's (OpenGL-style: a point is visible when −w ≤ x, y, z ≤ w, w = camera z)
with one deliberate choice: y_ndc = −1 is the TOP row of the image. nvdiffrast writes pixel row r at
y_ndc = (2r + 1)/H − 1, so its output then comes out top row first, exactly like saft's images — the same
thing as rendering with y up and flipping nvdiffrast's bottom-up output, without the flip. (The y flip
mirrors the winding of every triangle; both backends render two-sided, so nothing depends on winding.)

With the OpenCV camera (x right, y down, z forward; pixel (row i, col j) centred at u = j, v = i):

    x_ndc = (2 (u + 0.5) / W) − 1,    y_ndc = (2 (v + 0.5) / H) − 1,    w = z_cam,
    z_ndc = (f + n)/(f − n) − 2 f n / ((f − n) z_cam)        (−1 at the near plane, +1 at the far plane).
"""

from __future__ import annotations

import numpy as np
import torch

from saft.render.torch.rows import const
from saft.scene.camera import Camera, Crop


def projection_matrix(camera: Camera, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 matrix P with pos_clip = P @ [x_cam, y_cam, z_cam, 1]."""
    if not (0.0 < near < far):
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    W, H = camera.width, camera.height
    K = camera.K
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * K[0, 0] / W
    P[0, 1] = 2.0 * K[0, 1] / W  # skew, normally 0
    P[0, 2] = 2.0 * (K[0, 2] + 0.5) / W - 1.0
    P[1, 1] = 2.0 * K[1, 1] / H
    P[1, 2] = 2.0 * (K[1, 2] + 0.5) / H - 1.0
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def auto_near_far(z_cam: torch.Tensor) -> tuple[float, float]:
    """Near/far planes bracketing the given camera depths with margin (0.5×min, 2×max + 1 cm).

    Points at or behind the camera do not pull near below 1 mm. Nothing visible is clipped and the depth
    range stays tight, which keeps z/w precise (the metric depth saft returns does not depend on them).
    """
    if z_cam.numel() == 0:
        return 1e-3, 1.0
    near, far = _auto_near_far_tensors(z_cam.detach().to(torch.float64))  # float64: as Python floats
    return float(near), float(far)


def camera_to_clip(vertices: torch.Tensor, camera: Camera, *, crop: Crop | None = None,
                   scale: float | None = None, near: float | None = None,
                   far: float | None = None) -> torch.Tensor:
    """World-frame points (..., V, 3) → clip-space positions (..., V, 4) for `camera`.

    crop: render only that window of the camera's image (principal point shifted); scale: then resize the
    image by that factor (integer or arbitrary, e.g. 0.5 or 1/3, see Camera.scaled). The resolution to
    rasterize at is that of `effective_camera(camera, crop, scale)`. Differentiable with respect to
    `vertices`; keeps their dtype and device.

    near: default half the nearest camera depth of the points (at least 1 mm), computed on the device (no
    host sync), so nothing in front of the camera is clipped. far: default infinite, i.e. z_clip = w − 2·near
    and z/w = 1 − 2·near/w < 1 however far a point is (with near at half the nearest depth the depth test
    keeps about as many bits over the cloth as a far plane at twice its farthest depth did). With both
    given, the finite projection of projection_matrix(camera, near, far).

    One matrix product for x, y and w (world → clip composed once per camera) and one fused add for z: four
    kernels forward and one backward with the default planes. The per-call near and far planes of the
    earlier version cost about 30 launches forward and 10 backward, a third of a render step's launches on a
    GPU next to nvdiffrast (BENCHMARKS.md, "GPU, fourth session").
    """
    cam = effective_camera(camera, crop, scale)
    A, c = _camera_tensors(cam, vertices)  # rows x_clip, y_clip, w, w: the z row is made from w below
    clip = torch.addmm(c, vertices.reshape(-1, 3), A.T).reshape(*vertices.shape[:-1], 4)
    e_z = const((0.0, 0.0, 1.0, 0.0), clip)
    if near is None:
        w = clip[..., 3].detach()
        near_t = 0.5 * (w.amin().clamp_min(2e-3) if w.numel() else w.new_tensor(2e-3))
        if far is None:
            return torch.addcmul(clip, e_z, near_t, value=-2.0)  # z = w − 2 near
        a = (far + near_t) / (far - near_t)
        b = 2.0 * far * near_t / (far - near_t)
    elif far is None:
        return torch.add(clip, e_z, alpha=-2.0 * near)
    else:
        P = projection_matrix(cam, near, far)  # checks 0 < near < far
        a, b = P[2, 2], -P[2, 3]
    return torch.addcmul(clip, e_z, (a - 1.0) * clip[..., 3:4] - b)  # z = a w − b


_CAMERAS: dict = {}


def _camera_tensors(cam: Camera, like: torch.Tensor):
    """(A (4, 3), c (4,)) with A x + c = (x_clip, y_clip, w, w) for a world point x: world_to_camera and
    projection_matrix without its near/far-dependent z row (w in its place), composed in float64 and made
    once per camera as tensors of like's dtype and device (a host-to-device copy per frame otherwise)."""
    key = (cam.K.tobytes(), cam.world_to_camera.tobytes(), cam.width, cam.height, like.dtype, like.device)
    hit = _CAMERAS.get(key)
    if hit is None:
        P = projection_matrix(cam, 1.0, 2.0)
        P[2] = P[3]  # the z row depends on near and far: camera_to_clip makes it from w
        M = P @ np.asarray(cam.world_to_camera, dtype=np.float64)
        hit = tuple(torch.as_tensor(np.ascontiguousarray(a), dtype=like.dtype, device=like.device)
                    for a in (M[:, :3], M[:, 3]))
        if len(_CAMERAS) > 64:
            _CAMERAS.clear()
        _CAMERAS[key] = hit
    return hit


def _auto_near_far_tensors(z: torch.Tensor):
    """auto_near_far as 0-dim tensors on z's device (no host sync)."""
    zmax = z.amax()
    anyp = zmax > 0
    near = torch.where(anyp, (0.5 * z.masked_fill(z <= 0, torch.inf).amin()).clamp_min(1e-3), 1e-3)
    far = torch.where(anyp, torch.maximum(2.0 * zmax, near * 1.01) + 1e-2, 1.0)
    return near, far


def effective_camera(camera: Camera, crop: Crop | None = None, scale: float | None = None) -> Camera:
    """camera.cropped(crop).scaled(scale), skipping what is None."""
    cam = camera if crop is None else camera.cropped(crop)
    if scale is not None and scale != 1:
        cam = cam.scaled(scale)
    return cam
