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

    def validate(self) -> None:
        """Cross-checks between the parts (each reader also checks its own files)."""
        where = self.source
        if self.pinned is not None:
            p = np.asarray(self.pinned)
            if p.size and (p.min() < 0 or p.max() >= self.template.num_vertices):
                raise SaftInputError(
                    where, f"pinned vertex index {int(p.max() if p.max() >= self.template.num_vertices else p.min())} "
                    f"is out of range (the template has {self.template.num_vertices} vertices)")
        if self.frame_dt <= 0 or not np.isfinite(self.frame_dt):
            raise SaftInputError(where, f"time between frames must be positive, got {self.frame_dt}")
        if self.gravity is not None and (np.shape(self.gravity) != (3,) or not np.isfinite(self.gravity).all()):
            raise SaftInputError(where, "gravity must be three finite numbers")
        if (self.frames.width, self.frames.height) != (self.camera.width, self.camera.height):
            raise SaftInputError(
                where, f"frames are {self.frames.width}x{self.frames.height} but the camera says "
                f"{self.camera.width}x{self.camera.height}")
        if self.crop is not None:
            c = self.crop
            if c.top < 0 or c.left < 0 or c.height <= 0 or c.width <= 0 or \
                    c.top + c.height > self.camera.height or c.left + c.width > self.camera.width:
                raise SaftInputError(where, f"crop {c} does not fit in the {self.camera.width}x{self.camera.height} image")
        _, z = self.camera.project(self.template.vertices)
        if (z <= 0).any():
            raise SaftInputError(where, f"{int((z <= 0).sum())} template vertices are behind the camera; "
                                 "check world_to_camera (saft uses OpenCV: z forward, y down)")
