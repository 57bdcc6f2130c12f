"""What `saft view` shows, prepared from a result folder without any web library (plain numpy/PIL).

Everything here is in the result's world frame (metres). The viewer (saft.view.server) turns it into viser
scene nodes; keeping the preparation apart keeps it testable without a browser.
"""

from __future__ import annotations

import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from saft.errors import SaftInputError
from saft.evaluate import GroundTruthSpec, load_ground_truth_frames
from saft.export.figures import colour_bar_png
from saft.io_utils import read_image
from saft.result import Result, list_render_files, read_result
from saft.scene.camera import Camera

log = logging.getLogger("saft")

DISTANCE_CMAP = "viridis"
MATERIAL_MAPS = ("diffuse", "roughness", "metallic", "envmap")


@dataclass
class ViewData:
    """A result folder as the viewer needs it."""

    result: Result
    fps: float                                  # video frame rate 1/frame_dt
    up: np.ndarray                              # world up (unit), opposite gravity
    centre: np.ndarray                          # centre of the cloth's bounding box over all frames
    radius: float                               # half its diagonal (m)
    render_files: list[Path]                    # renders/frame_*.png (rendered | target | |difference|)
    material: dict[str, Path]                   # phase-3 maps present: diffuse, roughness, metallic, envmap
    gt_frames: list[np.ndarray] | None          # ground-truth point clouds (world frame) per frame
    gt_note: str                                # where the ground truth came from, or why there is none
    distances: np.ndarray | None                # (frames, V) distance of each vertex to the ground truth (m)

    @property
    def num_frames(self) -> int:
        return self.result.num_frames


def _up(res: Result) -> np.ndarray:
    up = res.up_direction()
    return np.array([0.0, -1.0, 0.0]) if up is None else np.asarray(up, dtype=np.float64)


def load_ground_truth(res: Result) -> tuple[list[np.ndarray] | None, str]:
    """The ground-truth clouds the result names (scene.json, else metrics.json), in the world frame.

    Returns (None, why) when there are none or their folder is not on this machine."""
    info = res.scene_info
    directory = info.get("ground_truth_dir") or (res.metrics or {}).get("ground_truth_dir")
    if not directory:
        return None, "the result names no ground truth"
    directory = Path(directory)
    if not directory.is_dir():
        return None, f"ground truth {directory} not found on this machine"
    frame = info.get("ground_truth_frame") or "world"
    if frame == "camera":
        full = info.get("full_camera") or info.get("camera")
        if full is None:
            return None, f"ground truth {directory} is in the camera frame, but scene.json has no camera"
        spec = GroundTruthSpec.in_camera_frame(directory, Camera.from_json(full))
    else:
        spec = GroundTruthSpec(directory, "world")
    try:
        frames = load_ground_truth_frames(spec)
    except SaftInputError as exc:
        return None, f"ground truth not readable: {exc}"
    return frames, f"ground truth: {directory} ({len(frames)} frames)"


def vertex_distances(vertices: np.ndarray, gt_frames: list[np.ndarray]) -> np.ndarray:
    """(frames, V) distance of every vertex to the nearest ground-truth point of its frame (m); NaN for
    frames without ground truth."""
    out = np.full(vertices.shape[:2], np.nan)
    for k in range(min(len(vertices), len(gt_frames))):
        out[k] = cKDTree(gt_frames[k]).query(vertices[k])[0]
    return out


def distance_scale(distances: np.ndarray) -> float:
    """The top of the colour scale (m): the 98th percentile of all distances, so that a few far vertices do
    not wash the map out."""
    ok = distances[np.isfinite(distances)]
    return max(float(np.percentile(ok, 98)), 1e-6) if ok.size else 1e-3


def colormap_strip(name: str = DISTANCE_CMAP, n: int = 256) -> np.ndarray:
    """(4, n, 3) uint8 image of a matplotlib colour map, left (0) to right (1): the texture of the
    distance colouring (a vertex's u coordinate is its distance / scale)."""
    import matplotlib

    rgb = matplotlib.colormaps[name](np.linspace(0.0, 1.0, n))[:, :3]
    return np.repeat((rgb * 255.0 + 0.5).astype(np.uint8)[None], 4, axis=0)


def distance_uvs(distances: np.ndarray, scale: float) -> np.ndarray:
    """(V, 2) texture coordinates into colormap_strip for one frame's distances (NaN → the middle row, u=0)."""
    u = np.clip(np.nan_to_num(distances / scale, nan=0.0), 0.0, 1.0) * 0.98 + 0.01
    return np.stack([u, np.full_like(u, 0.5)], axis=1)


def colour_bar(scale_m: float, name: str = DISTANCE_CMAP) -> np.ndarray:
    """An H×W×3 uint8 picture of the colour bar, labelled in millimetres."""
    with Image.open(io.BytesIO(colour_bar_png(0.0, scale_m * 1000.0, "distance to ground truth (mm)", name))) as im:
        return np.asarray(im.convert("RGB"))


def target_image(render_file: Path, camera: Camera | None) -> np.ndarray | None:
    """The input frame (the middle panel of renders/frame_*.png: rendered | target | |difference|), uint8."""
    img = read_image(render_file)[:, :, :3]
    w = camera.width if camera is not None and img.shape[1] == 3 * camera.width else img.shape[1] // 3
    if w < 1:
        return None
    return (np.clip(img[:, w:2 * w], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def frustum_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(wxyz quaternion, position, vertical field of view in radians, aspect) of an OpenCV camera, as viser's
    camera frustums take them (viser frustums look along +z with +y down, like OpenCV)."""
    c2w = camera.camera_to_world
    x, y, z, w = Rotation.from_matrix(c2w[:3, :3]).as_quat()
    fov = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return np.array([w, x, y, z]), c2w[:3, 3].copy(), fov, camera.width / camera.height


def load_view_data(result_dir: str | Path) -> ViewData:
    res = read_result(result_dir)
    pts = res.vertices.reshape(-1, 3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    material = {}
    for name in MATERIAL_MAPS:
        p = res.material_path(f"{name}.png")
        if p is not None:
            material[name] = p
    gt, note = load_ground_truth(res)
    distances = vertex_distances(res.vertices, gt) if gt else None
    if gt is not None and len(gt) != res.num_frames:
        note += f"; the result has {res.num_frames} frames"
    return ViewData(result=res, fps=1.0 / res.frame_dt if res.frame_dt > 0 else 25.0, up=_up(res),
                    centre=0.5 * (lo + hi), radius=max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3),
                    render_files=list_render_files(res.folder), material=material, gt_frames=gt, gt_note=note,
                    distances=distances)
