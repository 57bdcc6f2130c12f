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
    rasterize at is that of `effective_camera(camera, crop, scale)`. near/far default to auto_near_far's,
    computed on the device (no host sync). Differentiable with respect to `vertices`; keeps their dtype
    and device.
    """
    cam = effective_camera(camera, crop, scale)
    R, t, P0 = _camera_tensors(cam, vertices)
    p_cam = vertices @ R.T + t
    clip = torch.cat([p_cam, torch.ones_like(p_cam[..., :1])], dim=-1) @ P0.T  # z column 0: added below
    if near is None or far is None:  # 0-dim tensors on the device
        n_auto, f_auto = _auto_near_far_tensors(p_cam[..., 2].detach())
        near = n_auto if near is None else torch.full_like(n_auto, near)
        far = f_auto if far is None else torch.full_like(f_auto, far)
    # projection_matrix's z row: z_clip = (f + n)/(f − n) z − 2 f n/(f − n)
    zc = p_cam[..., 2:3] * ((far + near) / (far - near)) - 2.0 * far * near / (far - near)
    return clip + zc * const((0.0, 0.0, 1.0, 0.0), clip)


_CAMERAS: dict = {}


def _camera_tensors(cam: Camera, like: torch.Tensor):
    """world_to_camera's R (3, 3) and t (3,) and projection_matrix(cam, ·, ·) without its z row, as tensors
    of like's dtype and device, made once per camera (a host-to-device copy per frame otherwise)."""
    key = (cam.K.tobytes(), cam.world_to_camera.tobytes(), cam.width, cam.height, like.dtype, like.device)
    hit = _CAMERAS.get(key)
    if hit is None:
        P0 = projection_matrix(cam, 1.0, 2.0)
        P0[2] = 0.0  # the z row depends on near and far: camera_to_clip adds it
        hit = tuple(torch.as_tensor(np.ascontiguousarray(a), dtype=like.dtype, device=like.device)
                    for a in (cam.world_to_camera[:3, :3], cam.world_to_camera[:3, 3], P0))
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
