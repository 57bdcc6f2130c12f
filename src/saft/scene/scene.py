"""Scene: everything a reconstruction starts from, in saft's own conventions (see docs/architecture.md)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.scene.camera import Camera, Crop
from saft.scene.frames import FrameSequence
from saft.scene.mesh import QuadMesh

DEFAULT_FRAME_DT = 0.02  # seconds; what the reference method assumes for the φ-SfT videos
# Plausible time between frames: 10 000 fps (high-speed cameras) to 1 fps (a time-lapse). Outside this, the
# value is almost surely in the wrong unit (milliseconds, frames per second given as frame_dt, …).
FRAME_DT_RANGE = (1e-4, 1.0)
# The smallest working image (after the crop) saft accepts, in pixels per side: below it the silhouette of
# the cloth is a handful of pixels and the reconstruction is meaningless.
MIN_IMAGE_SIDE = 16
STANDARD_GRAVITY = 9.81


@dataclass(frozen=True)
class Scene:
    """A template mesh, a camera and a video.

    template:      frame-0 shape of the cloth (world frame, metres)
    camera:        the camera of the FULL frames (crop is applied by `working_camera`)
    frames:        the video (full frames; `working_frames` applies the crop)
    texture:       optional (H, W, 3) float32 sRGB texture image, row 0 = top (v = 1)
    pinned:        optional template vertex indices held in place
    frame_dt:      seconds between consecutive frames
    gravity:       optional (3,) gravity vector in the world frame (m/s²)
    crop:          optional window of the full frames that the reconstruction works on
    ground_truth_dir / ground_truth_frame: optional per-frame point clouds for evaluation and the frame
                   ("world" or "camera") they are stored in
    """

    name: str
    template: QuadMesh
    camera: Camera
    frames: FrameSequence
    texture: np.ndarray | None = None
    pinned: np.ndarray | None = None
    frame_dt: float = DEFAULT_FRAME_DT
    gravity: np.ndarray | None = None
    crop: Crop | None = None
    source: Path | None = None
    ground_truth_dir: Path | None = None
    ground_truth_frame: str = "world"

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    def gravity_or_default(self) -> np.ndarray:
        """The scene's gravity, else 9.81 m/s² opposite to the camera's image-up direction."""
        if self.gravity is not None:
            return np.asarray(self.gravity, dtype=np.float64)
        return -STANDARD_GRAVITY * self.camera.up

    def working_camera(self, scale: float = 1.0) -> Camera:
        cam = self.camera.cropped(self.crop) if self.crop else self.camera
        return cam.scaled(scale) if scale != 1.0 else cam

    def working_frames(self, scale: float = 1.0) -> FrameSequence:
        return self.frames.view(self.crop, scale)

    def with_frames(self, count: int) -> "Scene":
        """The scene restricted to its first `count` frames."""
        f = self.frames
        masks = f.mask_paths[:count] if f.mask_paths else None
        return replace(self, frames=replace(f, rgb_paths=f.rgb_paths[:count], mask_paths=masks))

    def with_template_noise(self, seed: int, sigma: float = 1e-9) -> "Scene":
        """The scene with its template moved by seeded Gaussian noise of `sigma` metres: a perturbation that
        should not matter, to repeat a deterministic reconstruction (the benchmarks' perturbed runs)."""
        noise = np.random.default_rng(seed).normal(0.0, sigma, self.template.vertices.shape)
        return replace(self, template=replace(self.template, vertices=self.template.vertices + noise))

    def validate(self, meta_source: Path | None = None) -> None:
        """Cross-checks between the parts (each reader also checks its own files). Problems with frame_dt,
        pinned vertices, gravity and the crop name `meta_source` (the file that gave them), others the scene."""
        where = meta_source or self.source
        if self.pinned is not None:
            p = np.asarray(self.pinned)
            if p.size and (p.min() < 0 or p.max() >= self.template.num_vertices):
                raise SaftInputError(
                    where, f"pinned vertex index {int(p.max() if p.max() >= self.template.num_vertices else p.min())} "
                    f"is out of range (the template has {self.template.num_vertices} vertices)")
        lo, hi = FRAME_DT_RANGE
        if not (np.isfinite(self.frame_dt) and lo <= self.frame_dt <= hi):
            raise SaftInputError(where, f"time between frames (frame_dt) must lie in [{lo:g}, {hi:g}] s "
                                        f"(1 to 10000 fps), got {self.frame_dt:g}")
        if self.gravity is not None and (np.shape(self.gravity) != (3,) or not np.isfinite(self.gravity).all()):
            raise SaftInputError(where, "gravity must be three finite numbers")
        where = self.source
        if (self.frames.width, self.frames.height) != (self.camera.width, self.camera.height):
            raise SaftInputError(
                where, f"frames are {self.frames.width}x{self.frames.height} but the camera says "
                f"{self.camera.width}x{self.camera.height}")
        if self.crop is not None:
            c = self.crop
            if c.top < 0 or c.left < 0 or c.height <= 0 or c.width <= 0 or \
                    c.top + c.height > self.camera.height or c.left + c.width > self.camera.width:
                raise SaftInputError(meta_source or where, f"crop {c.to_json()} does not fit in the "
                                                           f"{self.camera.width}x{self.camera.height} image")
        cam = self.working_camera()
        if min(cam.width, cam.height) < MIN_IMAGE_SIDE:
            raise SaftInputError(meta_source if self.crop else where,
                                 f"the working image ({'crop' if self.crop else 'frame'}) is only "
                                 f"{cam.width}x{cam.height} pixels; saft needs at least "
                                 f"{MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}")
        z = cam.world_to_cam_points(self.template.vertices)[:, 2]
        if (z <= 0).any():
            raise SaftInputError(where, f"{int((z <= 0).sum())} template vertices are behind the camera; "
                                 "check world_to_camera (saft uses OpenCV: z forward, y down)")
        uv, _ = cam.project(self.template.vertices)
        inside = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5)
                  & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5))
        if not inside.any():
            lo_uv, hi_uv = uv.min(axis=0), uv.max(axis=0)
            raise SaftInputError(
                where, f"the template projects entirely outside the {cam.width}x{cam.height} working image "
                f"(columns {lo_uv[0]:.0f}..{hi_uv[0]:.0f}, rows {lo_uv[1]:.0f}..{hi_uv[1]:.0f}); check the principal "
                "point, world_to_camera and the crop")
