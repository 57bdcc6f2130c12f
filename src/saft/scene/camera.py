"""Camera: OpenCV pinhole intrinsics + a rigid world_to_camera transform, with crop and rescale.

Convention (the only one inside saft): camera frame x right, y down, z forward; the pixel in row i,
column j has its centre at (u = j, v = i). Readers convert every other convention into this one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from saft.errors import SaftInputError


@dataclass(frozen=True)
class Crop:
    """A pixel window of an image: rows top..top+height-1, columns left..left+width-1."""

    top: int
    left: int
    height: int
    width: int

    def as_slices(self) -> tuple[slice, slice]:
        return slice(self.top, self.top + self.height), slice(self.left, self.left + self.width)

    def to_json(self) -> dict:
        return {"top": self.top, "left": self.left, "height": self.height, "width": self.width}


@dataclass(frozen=True)
class Camera:
    """K: (3, 3) intrinsics; world_to_camera: (4, 4) rigid transform; image size in pixels."""

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "world_to_camera", np.asarray(self.world_to_camera, dtype=np.float64).reshape(4, 4))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ---------------------------------------------------------------- construction and checks
    @staticmethod
    def from_intrinsics(fx: float, fy: float, cx: float, cy: float, world_to_camera, width: int, height: int,
                        source: str | None = None) -> "Camera":
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cam = Camera(K, np.asarray(world_to_camera, dtype=np.float64), width, height)
        cam.validate(source)
        return cam

    def validate(self, source: str | None = None) -> None:
        """Raise SaftInputError (naming `source`) unless the camera is usable."""
        if self.width <= 0 or self.height <= 0:
            raise SaftInputError(source, f"image size must be positive, got {self.width}x{self.height}")
        if not (np.isfinite(self.K).all() and np.isfinite(self.world_to_camera).all()):
            raise SaftInputError(source, "camera contains NaN or inf")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise SaftInputError(source, "focal lengths must be positive")
        if abs(self.cx - 0.5 * self.width) > self.width or abs(self.cy - 0.5 * self.height) > self.height:
            raise SaftInputError(
                source, f"principal point (cx, cy) = ({self.cx:g}, {self.cy:g}) lies far outside the "
                f"{self.width}x{self.height} image; cx, cy are pixel coordinates (column, row), usually near the centre")
        R = self.world_to_camera[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or abs(np.linalg.det(R) - 1.0) > 1e-4:
            raise SaftInputError(source, "world_to_camera is not a rigid transform (its 3x3 part is not a rotation)")
        if not np.allclose(self.world_to_camera[3], [0, 0, 0, 1], atol=1e-8):
            raise SaftInputError(source, "world_to_camera must have last row [0, 0, 0, 1]")

    # ---------------------------------------------------------------- properties
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def rotation(self) -> np.ndarray:
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """Camera position in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def camera_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_camera)

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (camera +z) in world coordinates."""
        return self.rotation[2].copy()

    @property
    def up(self) -> np.ndarray:
        """Image-up direction (camera -y) in world coordinates."""
        return -self.rotation[1]

    # ---------------------------------------------------------------- geometry
    def world_to_cam_points(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return points @ self.rotation.T + self.translation

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) → pixel coordinates (N, 2) as (u = column, v = row), and depth z (N,)."""
        pc = self.world_to_cam_points(points)
        z = pc[:, 2]
        u = self.fx * pc[:, 0] / z + self.cx
        v = self.fy * pc[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def cropped(self, crop: Crop) -> "Camera":
        """The camera of a sub-window: principal point shifted, image size that of the window."""
        K = self.K.copy()
        K[0, 2] -= crop.left
        K[1, 2] -= crop.top
        return Camera(K, self.world_to_camera, crop.width, crop.height)

    def scaled(self, factor: float) -> "Camera":
        """The camera of the image resized by `factor` (any positive number, e.g. 0.5 or 1/3).

        The new size is rounded to whole pixels and the intrinsics use the exact per-axis ratio, keeping
        pixel centres consistent: u' = (u + 0.5)·s − 0.5.
        """
        if factor <= 0:
            raise ValueError("scale factor must be positive")
        width = max(1, int(round(self.width * factor)))
        height = max(1, int(round(self.height * factor)))
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(K, self.world_to_camera, width, height)

    @staticmethod
    def from_json(data: dict) -> "Camera":
        """Inverse of to_json."""
        return Camera(np.asarray(data["K"], dtype=np.float64), np.asarray(data["world_to_camera"], dtype=np.float64),
                      int(data["width"]), int(data["height"]))

    def to_json(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "world_to_camera": self.world_to_camera.tolist(),
        }


def look_at(eye, target, up, K: np.ndarray, width: int, height: int) -> Camera:
    """An OpenCV camera at `eye` looking at `target` with image-up roughly along `up` (world frame)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # camera x (image right) = forward × up for a y-down camera
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # camera y points down in the image
    R = np.stack([x, y, z], axis=0)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return Camera(K, T, width, height)


# ---------------------------------------------------------------------------------------------- orbits
def up_direction(gravities, camera: Camera | None) -> np.ndarray | None:
    """The world's up: opposite the first usable vector of `gravities` (each None or 3 numbers), else the
    camera's image-up, else None."""
    for g in gravities:
        if g is not None:
            g = np.asarray(g, dtype=np.float64).reshape(-1)
            if g.shape == (3,) and np.linalg.norm(g) > 0:
                return -g / np.linalg.norm(g)
    if camera is not None:
        return camera.up / np.linalg.norm(camera.up)
    return None


def orbit_camera(camera: Camera, center, angle_deg: float, axis=None) -> Camera:
    """The camera turned by `angle_deg` around the vertical axis through `center` (world point).

    axis defaults to the camera's image-up direction (world). Intrinsics and image size are kept.
    """
    c = np.asarray(center, dtype=np.float64).reshape(3)
    a = np.asarray(camera.up if axis is None else axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    th = np.radians(angle_deg)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = c - R @ c
    c2w = M @ camera.camera_to_world
    w2c = np.linalg.inv(c2w)
    w2c[3] = [0, 0, 0, 1]
    return Camera(camera.K, w2c, camera.width, camera.height)


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def orbit_cameras(points: np.ndarray, camera: Camera | None, up: np.ndarray | None, n: int, width: int,
                  height: int) -> list[Camera]:
    """n cameras on a full circle about the `up` axis (default −y) through the centre of `points` (…, 3),
    looking at the centre, starting from the direction of `camera` (if any)."""
    pts = np.asarray(points).reshape(-1, 3)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    radius = max(float(np.linalg.norm(pts - centre, axis=1).max()), 1e-3)
    up = np.array([0.0, -1.0, 0.0]) if up is None else up
    if camera is not None:
        offset = camera.center - centre
    else:
        side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
        offset = side / np.linalg.norm(side)
    horiz = offset - (offset @ up) * up
    if np.linalg.norm(horiz) < 0.2 * np.linalg.norm(offset):  # looking straight along up: tilt to 30°
        ref = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
        horiz = ref / np.linalg.norm(ref)
        offset = math.cos(math.radians(30)) * horiz + math.sin(math.radians(30)) * up * np.sign(offset @ up or 1.0)
    offset = offset / np.linalg.norm(offset) * radius * 3.0
    dist = np.linalg.norm(offset)
    half_fov = math.atan(1.05 * radius / math.sqrt(max(dist ** 2 - radius ** 2, 1e-12)))
    f = 0.5 * min(width, height) / math.tan(half_fov)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return [look_at(centre + axis_rotation(up, 2 * math.pi * i / n) @ offset, centre, up, K, width, height)
            for i in range(n)]
