"""Reader of the SAFT / PG-SfT scene JSONs of the φ-SfT real scenes (R1.json … R9.json).

Conventions of that layout (checked numerically on R1, see ../shared/data/phi_sft/README.md):
- file paths are relative to a folder `code/` beside `data/` (the authors ran their scripts from there);
- the template frame is a camera frame given by camera_positions / camera_directions / camera_ups, with
  image-right = direction × up; we turn it into an OpenCV world_to_camera once, here;
- intrinsics are ordered (row, column): focal_lengths = [f_row, f_col], optical_centers = [c_row, c_col],
  image_size = [height, width];
- lower_left_corners / upper_right_corners are (row, column) with rows counted from the BOTTOM;
- ground-truth point clouds are stored in the OpenCV camera frame (x, y negated w.r.t. the template);
- no gravity is given (Scene.gravity None): the reconstruction assumes 9.81 m/s² opposite to the camera's up
  vector (Scene.gravity_or_default).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import read_image
from saft.scene.camera import Camera, Crop
from saft.scene.frames import FrameSequence, list_images
from saft.scene.mesh import read_obj
from saft.scene.native import read_json
from saft.scene.scene import DEFAULT_FRAME_DT, STANDARD_GRAVITY, Scene

PATH_KEYS = ("mesh_file", "image_files", "mask_files", "texture_file", "ground_truth_dir")
REQUIRED_KEYS = ("mesh_file", "image_files", "camera_positions", "camera_directions", "camera_ups",
                 "optical_centers", "focal_lengths", "image_size")


def _code_dir(json_path: Path, data: dict, root: Path | None) -> Path:
    """The folder the JSON's relative paths start from."""
    if root is not None:
        candidates = [root / "code", root]
    else:
        candidates = [json_path.parent.parent.parent / "code", json_path.parent.parent / "code",
                      json_path.parent, Path.cwd()]
    for c in candidates:
        if (c / data["mesh_file"]).resolve().is_file():
            return c
    raise SaftInputError(
        json_path, f"cannot find {data['mesh_file']!r}: paths in this JSON are relative to a folder 'code/' "
        "beside 'data/'; pass the dataset root explicitly (--root) if the layout differs")


def _first_row(json_path: Path, data: dict, key: str, length: int) -> np.ndarray:
    try:
        arr = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise SaftInputError(json_path, f"{key!r} must hold numbers") from None
    arr = arr.reshape(-1, length) if arr.size % length == 0 and arr.size else None
    if arr is None:
        raise SaftInputError(json_path, f"{key!r} must be a list of {length}-vectors")
    return arr[0]


def camera_from_phi_sft(json_path: Path, data: dict) -> Camera:
    position = _first_row(json_path, data, "camera_positions", 3)
    direction = _first_row(json_path, data, "camera_directions", 3)
    up = _first_row(json_path, data, "camera_ups", 3)
    f_row, f_col = _first_row(json_path, data, "focal_lengths", 2)
    c_row, c_col = _first_row(json_path, data, "optical_centers", 2)
    size = _first_row(json_path, data, "image_size", 2)
    if not (np.isfinite(size).all() and (size == np.round(size)).all() and (size > 0).all() and (size < 1e6).all()):
        raise SaftInputError(json_path, f"'image_size' must be [height, width] in whole pixels, got {size.tolist()}")
    height, width = (int(v) for v in size)
    for name, vec in (("camera_positions", position), ("camera_directions", direction), ("camera_ups", up),
                      ("focal_lengths", [f_row, f_col]), ("optical_centers", [c_row, c_col])):
        if not np.isfinite(vec).all():
            raise SaftInputError(json_path, f"{name!r} must hold finite numbers")
    if np.linalg.norm(direction) < 1e-12:
        raise SaftInputError(json_path, "'camera_directions' must not be zero")
    z = direction / np.linalg.norm(direction)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise SaftInputError(json_path, "camera direction and up vector are parallel")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # = -up, orthogonalised
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ position
    return Camera.from_intrinsics(f_col, f_row, c_col, c_row, w2c, width, height, source=str(json_path))


def crop_from_phi_sft(json_path: Path, data: dict, image_height: int) -> Crop | None:
    if "lower_left_corners" not in data or "upper_right_corners" not in data:
        return None
    r0, c0 = _first_row(json_path, data, "lower_left_corners", 2)
    r1, c1 = _first_row(json_path, data, "upper_right_corners", 2)
    if not np.isfinite([r0, c0, r1, c1]).all() or max(abs(r0), abs(c0), abs(r1), abs(c1)) > 1e6:
        raise SaftInputError(json_path, "crop corners must be finite pixel positions")
    return Crop(top=int(image_height - r1), left=int(c0), height=int(r1 - r0), width=int(c1 - c0))


def read_phi_sft_scene(json_path: str | Path, root: str | Path | None = None) -> Scene:
    json_path = Path(json_path)
    data = read_json(json_path)
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise SaftInputError(json_path, f"missing key(s) {', '.join(missing)} of the SAFT/PG-SfT scene layout")
    for key in PATH_KEYS:
        if key in data and (not isinstance(data[key], str) or not data[key] or "\0" in data[key]):
            raise SaftInputError(json_path, f"{key!r} must be a relative path (a non-empty string)")
    n_images = data.get("n_images")
    if n_images is not None and (not isinstance(n_images, int) or isinstance(n_images, bool) or n_images < 1):
        raise SaftInputError(json_path, f"'n_images' must be a positive whole number, got {n_images!r}")
    code = _code_dir(json_path, data, Path(root) if root is not None else None)

    def resolve(key: str) -> Path:
        return (code / data[key]).resolve()

    template = read_obj(resolve("mesh_file"))
    camera = camera_from_phi_sft(json_path, data)
    rgb_paths = list_images(resolve("image_files"))
    mask_paths = list_images(resolve("mask_files")) if "mask_files" in data else None
    n = len(rgb_paths) if n_images is None else n_images
    if len(rgb_paths) < n:
        raise SaftInputError(resolve("image_files"), f"has {len(rgb_paths)} frames but the JSON says n_images={n}")
    rgb_paths = rgb_paths[:n]
    if mask_paths is not None:
        if len(mask_paths) < n:
            raise SaftInputError(resolve("mask_files"), f"has {len(mask_paths)} masks for {n} frames")
        mask_paths = mask_paths[:n]
    frames = FrameSequence(tuple(rgb_paths), tuple(mask_paths) if mask_paths else None, camera.width, camera.height)

    texture = None
    if "texture_file" in data and resolve("texture_file").is_file():
        texture = read_image(resolve("texture_file"))
        texture = np.repeat(texture, 3, axis=2) if texture.shape[2] == 1 else texture[:, :, :3]

    gt_dir = resolve("ground_truth_dir") if "ground_truth_dir" in data else None
    if gt_dir is not None and not gt_dir.is_dir():
        gt_dir = None
    scene = Scene(
        name=str(data.get("scene", json_path.stem)), template=template, camera=camera, frames=frames,
        texture=texture, pinned=None, frame_dt=DEFAULT_FRAME_DT,
        gravity=None, crop=crop_from_phi_sft(json_path, data, camera.height),
        source=json_path, ground_truth_dir=gt_dir, ground_truth_frame="camera",
    )
    scene.validate()
    return scene
