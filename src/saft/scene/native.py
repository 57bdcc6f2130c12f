"""Reader and writer of saft's native scene folder (documented in README.md, "Scene format").

    scene/
      template.obj     quad faces with vt (frame-0 shape, metres)
      camera.json      {"width", "height", "K": 3x3 (or "fx","fy","cx","cy"), "world_to_camera": 4x4}
      rgb/*.png        frames in sorted order
      mask/*.png       optional; 0 = background
      texture.png      optional
      scene.json       optional: "name" (default: the folder's), {"fps"} or {"frame_dt"}, "pinned_vertices", "gravity", "crop",
                       "ground_truth": {"dir": "gt", "frame": "world" | "camera"}
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import atomic_save_npy, atomic_write_json, read_image, write_image
from saft.scene.camera import Camera, Crop
from saft.scene.frames import check_all_frames, frame_sequence_from_folders
from saft.scene.mesh import read_obj, write_obj
from saft.scene.scene import DEFAULT_FRAME_DT, Scene


def read_json(path: Path) -> dict:
    if not path.is_file():
        raise SaftInputError(path, "file not found")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SaftInputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SaftInputError(path, "expected a JSON object at the top level")
    return data


def _number(path: Path, data: dict, key: str) -> float:
    try:
        value = float(data[key])
    except KeyError:
        raise SaftInputError(path, f"missing key {key!r}") from None
    except (TypeError, ValueError):
        raise SaftInputError(path, f"{key!r} must be a number") from None
    if not np.isfinite(value):
        raise SaftInputError(path, f"{key!r} must be finite")
    return value


def _whole(value) -> int:
    """A JSON whole number (3 or 3.0); ValueError for anything else (fractions, inf, text, true)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value != int(value):
        raise ValueError(f"not a whole number: {value!r}")
    return int(value)


def _matrix(path: Path, data: dict, key: str, shape: tuple[int, int]) -> np.ndarray:
    if key not in data:
        raise SaftInputError(path, f"missing key {key!r}")
    try:
        m = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise SaftInputError(path, f"{key!r} must be a {shape[0]}x{shape[1]} matrix of numbers") from None
    if m.shape != shape:
        raise SaftInputError(path, f"{key!r} must be {shape[0]}x{shape[1]}, got shape {m.shape}")
    return m


def read_camera_json(path: Path) -> Camera:
    data = read_json(path)
    width, height = _number(path, data, "width"), _number(path, data, "height")
    if width != int(width) or height != int(height):
        raise SaftInputError(path, "width and height must be whole numbers")
    if "K" in data:
        K = _matrix(path, data, "K", (3, 3))
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if not np.isfinite(K).all():
            raise SaftInputError(path, "'K' contains NaN or inf")
        if not np.any(K):
            raise SaftInputError(path, "'K' is all zeros; give [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels")
        if not np.allclose(K[2], [0, 0, 1]):
            raise SaftInputError(path, f"the last row of 'K' must be [0, 0, 1], got {K[2].tolist()}")
        if fx <= 0 or fy <= 0:
            raise SaftInputError(path, f"'K' must have positive focal lengths K[0][0], K[1][1], got {fx:g}, {fy:g}")
        if abs(K[0, 1]) > 1e-9 or abs(K[1, 0]) > 1e-9:
            raise SaftInputError(path, "K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    else:
        fx, fy, cx, cy = (_number(path, data, k) for k in ("fx", "fy", "cx", "cy"))
    w2c = _matrix(path, data, "world_to_camera", (4, 4))
    return Camera.from_intrinsics(fx, fy, cx, cy, w2c, int(width), int(height), source=str(path))


def read_native_scene(folder: str | Path) -> Scene:
    folder = Path(folder)
    if not folder.is_dir():
        raise SaftInputError(folder, "scene folder not found")
    template = read_obj(folder / "template.obj")
    camera = read_camera_json(folder / "camera.json")
    mask_dir = folder / "mask"
    frames = frame_sequence_from_folders(folder / "rgb", mask_dir if mask_dir.exists() else None,
                                         (camera.width, camera.height), folder / "camera.json")
    check_all_frames(frames)

    texture = None
    if (folder / "texture.png").exists():
        texture = read_image(folder / "texture.png")
        texture = np.repeat(texture, 3, axis=2) if texture.shape[2] == 1 else texture[:, :, :3]

    meta_path = folder / "scene.json"
    meta = read_json(meta_path) if meta_path.exists() else {}
    frame_dt = DEFAULT_FRAME_DT
    if "frame_dt" in meta:
        frame_dt = _number(meta_path, meta, "frame_dt")
    elif "fps" in meta:
        fps = _number(meta_path, meta, "fps")
        if fps <= 0:
            raise SaftInputError(meta_path, "'fps' must be positive")
        frame_dt = 1.0 / fps
    pinned = None
    if "pinned_vertices" in meta:
        raw = meta["pinned_vertices"]
        if not isinstance(raw, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in raw):
            raise SaftInputError(meta_path, f"'pinned_vertices' must be a list of whole vertex indices (0-based), "
                                            f"got {json.dumps(raw)[:60]}")
        pinned = np.asarray(raw, dtype=np.int64).reshape(-1) if all(abs(i) < 2 ** 62 for i in raw) else None
        if pinned is None:
            raise SaftInputError(meta_path, "a 'pinned_vertices' index is out of range")
        if pinned.size and (pinned.min() < 0 or pinned.max() >= template.num_vertices):
            bad = int(pinned.max() if pinned.max() >= template.num_vertices else pinned.min())
            raise SaftInputError(meta_path, f"pinned vertex index {bad} is out of range "
                                            f"(template.obj has {template.num_vertices} vertices)")
    gravity = None
    if "gravity" in meta:
        try:
            gravity = np.asarray(meta["gravity"], dtype=np.float64)
        except (TypeError, ValueError):
            gravity = None
        if gravity is None or gravity.shape != (3,) or not np.isfinite(gravity).all():
            raise SaftInputError(meta_path, "'gravity' must be [gx, gy, gz] in m/s²")
    crop = None
    if "crop" in meta:
        c = meta["crop"]
        try:
            crop = Crop(*(_whole(c[k]) for k in ("top", "left", "height", "width")))
        except (TypeError, KeyError, ValueError):
            raise SaftInputError(meta_path, "'crop' must be {\"top\", \"left\", \"height\", \"width\"} in pixels") from None
    gt_dir, gt_frame = None, "world"
    if "ground_truth" in meta:
        gt = meta["ground_truth"]
        if not isinstance(gt, dict) or not isinstance(gt.get("dir"), str) or not gt["dir"] or "\0" in gt["dir"]:
            raise SaftInputError(meta_path, "'ground_truth' must be {\"dir\": ..., \"frame\": \"world\"|\"camera\"}")
        gt_dir = (folder / gt["dir"]).resolve()
        gt_frame = gt.get("frame", "world")
        if gt_frame not in ("world", "camera"):
            raise SaftInputError(meta_path, "'ground_truth.frame' must be \"world\" or \"camera\"")
    elif (folder / "gt").is_dir():
        gt_dir = (folder / "gt").resolve()

    name = meta.get("name")
    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise SaftInputError(meta_path, "'name' must be a non-empty string")
    scene = Scene(
        name=name.strip() if name else folder.resolve().name, template=template, camera=camera, frames=frames,
        texture=texture, pinned=pinned, frame_dt=frame_dt, gravity=gravity, crop=crop, source=folder,
        ground_truth_dir=gt_dir, ground_truth_frame=gt_frame,
    )
    scene.validate(meta_path if meta_path.exists() else None)
    return scene


def write_native_scene(folder: str | Path, scene: Scene, rgb: np.ndarray, mask: np.ndarray | None = None,
                       ground_truth: list[np.ndarray] | None = None) -> Path:
    """Write a scene (e.g. a synthetic one) in the native layout. rgb: (F, H, W, 3) sRGB, mask (F, H, W).

    Ground-truth point clouds, if given, go to gt/frame_XXX.npy in the world frame.
    """
    folder = Path(folder)
    write_obj(folder / "template.obj", scene.template, comment="saft scene template (metres)")
    atomic_write_json(folder / "camera.json", scene.camera.to_json())
    n = len(rgb)
    digits = max(3, len(str(n - 1)))
    for i in range(n):
        write_image(folder / "rgb" / f"{i:0{digits}d}.png", rgb[i])
        if mask is not None:
            write_image(folder / "mask" / f"{i:0{digits}d}.png", mask[i])
    if scene.texture is not None:
        write_image(folder / "texture.png", scene.texture)
    meta: dict = {"frame_dt": scene.frame_dt}
    if scene.pinned is not None:
        meta["pinned_vertices"] = [int(i) for i in scene.pinned]
    if scene.gravity is not None:
        meta["gravity"] = [float(g) for g in scene.gravity]
    if scene.crop is not None:
        meta["crop"] = scene.crop.to_json()
    if ground_truth is not None:
        for i, pts in enumerate(ground_truth):
            atomic_save_npy(folder / "gt" / f"frame_{i:0{digits}d}.npy", np.asarray(pts, dtype=np.float32))
        meta["ground_truth"] = {"dir": "gt", "frame": "world"}
    atomic_write_json(folder / "scene.json", meta)
    return folder
