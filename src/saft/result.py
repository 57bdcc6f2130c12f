"""The result folder of a reconstruction: its layout, and reading it back.

    DIR/
      config.toml            the full typed config the run used
      scene.json             what was reconstructed: scene name and source, working camera, crop, frame_dt
      meshes/frame_000.obj   one quad OBJ per input frame, with UVs, in the scene's world frame (metres);
      meshes/cloth.mtl       … each referring to this material (diffuse = ../texture.png)
      texture.png            the texture of phase 1 (sRGB)
      params.json            Y, B, S (and log10), constant acceleration, damping, frame_dt, substeps
      forces.npy             (N-1, V, 3) per-vertex, per-frame accelerations (m/s²) of phase 2
      renders/frame_000.png  rendered | target | |difference| per frame
      log.csv                per epoch: phase, epoch, frames in use, each loss term, seconds
      timings.json           seconds per phase
      metrics.json           with ground truth: per-frame and mean CD2, CD1, p2s, depth δ (saft evaluate)
      depth/frame_000.npz    with ground truth (saft evaluate): arrays `rendered` and `target`, H×W depth in
                             metres along the camera z axis of the working camera (resized to about two
                             ground-truth points per pixel), NaN or 0 where there is no cloth: the mesh
                             rasterized and the ground-truth cloud projected (the pairs compared for depth_cm)
      material/              phase 3: diffuse.png, roughness.png, metallic.png, envmap.exr (+ envmap.png),
                             renders/frame_000.png re-renders, novel_view.png
      checkpoint/            state for --resume (removed only by the user or by --overwrite)
      report.html            saft report (saft.export); export/ holds what `saft export` writes by default

Every file is written atomically (saft.io_utils), so an interrupted run never leaves a half-written one.
"""

from __future__ import annotations

import csv
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.io_utils import atomic_path, read_image
from saft.scene.camera import Camera, up_direction
from saft.scene.mesh import QuadMesh, read_obj

MESH_DIR = "meshes"
MESH_MTL = "cloth.mtl"


def mesh_path(result_dir: str | Path, frame: int) -> Path:
    return Path(result_dir) / MESH_DIR / f"frame_{frame:03d}.obj"


def list_mesh_files(result_dir: str | Path) -> list[Path]:
    """meshes/frame_000.obj … in frame order; SaftInputError unless the frame numbers run 0, 1, … without
    a gap and match the frame count that scene.json states (an incomplete or mixed result)."""
    folder = Path(result_dir) / MESH_DIR
    if not folder.is_dir():
        raise SaftInputError(folder, "no meshes/ folder: not a saft result (expected meshes/frame_000.obj …)")
    files = list(folder.glob("frame_*.obj"))
    if not files:
        raise SaftInputError(folder, "no frame_*.obj meshes in this folder")
    return check_frame_numbers(files, Path(result_dir))


def check_frame_numbers(files: list[Path], result_dir: Path) -> list[Path]:
    """`files` named frame_<number>.<ext>, sorted by number; SaftInputError naming the first missing frame."""
    numbered = {}
    for f in files:
        digits = f.stem[len("frame_"):]
        if not digits.isdigit():
            raise SaftInputError(f, "is not named frame_<number>: not a file of a saft result")
        if int(digits) in numbered:
            raise SaftInputError(f, f"is frame {int(digits)} again (also {numbered[int(digits)].name})")
        numbered[int(digits)] = f
    expected = len(numbered)
    info = result_dir / "scene.json"
    if info.is_file():
        stated = _read_json_opt(info).get("num_frames")
        if isinstance(stated, int) and not isinstance(stated, bool):
            expected = max(expected, stated)
    missing = [i for i in range(expected) if i not in numbered]
    if missing:
        sample = files[0]
        name = sample.parent / f"frame_{missing[0]:03d}{sample.suffix}"
        raise SaftInputError(name, f"is missing: the result has {len(numbered)} of {expected} frames "
                                   f"({len(missing)} missing); it is incomplete, run the reconstruction again")
    return [numbered[i] for i in range(expected)]


def list_render_files(result_dir: str | Path, material: bool = False) -> list[Path]:
    """renders/frame_*.png (or material/renders/frame_*.png), sorted; [] when there are none."""
    folder = Path(result_dir) / ("material/renders" if material else "renders")
    return sorted(folder.glob("frame_*.png")) if folder.is_dir() else []


def list_depth_files(result_dir: str | Path) -> list[Path]:
    """depth/frame_*.npz, sorted; [] without depth ground truth."""
    folder = Path(result_dir) / "depth"
    return sorted(folder.glob("frame_*.npz")) if folder.is_dir() else []


def read_depth_pair(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(rendered, target) depth maps (H×W float, metres, NaN or 0 = no cloth) of one depth/frame_*.npz."""
    path = Path(path)
    try:
        with np.load(path) as data:
            rendered, target = np.asarray(data["rendered"], dtype=np.float64), np.asarray(data["target"], dtype=np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise SaftInputError(path, f"not a depth pair with arrays 'rendered' and 'target' ({exc})") from None
    if rendered.ndim != 2 or rendered.shape != target.shape:
        raise SaftInputError(path, f"depth maps must be two H×W arrays of one size, got {rendered.shape} and {target.shape}")
    return rendered, target


def write_depth_pair(result_dir: str | Path, frame: int, rendered: np.ndarray, target: np.ndarray) -> Path:
    """Write depth/frame_XXX.npz (float32, compressed) atomically; the inverse of read_depth_pair."""
    path = Path(result_dir) / "depth" / f"frame_{frame:03d}.npz"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, rendered=rendered.astype(np.float32), target=target.astype(np.float32))
    return path


def mtl_text(texture_rel: str = "../texture.png") -> str:
    return ("# saft cloth material\nnewmtl cloth\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
            f"map_Kd {texture_rel}\n")


@dataclass
class Result:
    """A result folder read back (what export, report and evaluate need)."""

    folder: Path
    template: QuadMesh                 # topology + UVs (vertices of frame 0)
    vertices: np.ndarray               # (N, V, 3) float64, world frame
    frame_dt: float
    texture: np.ndarray | None         # (H, W, 3) sRGB
    params: dict
    camera: Camera | None
    scene_info: dict
    config_text: str | None
    log_rows: list[dict]
    metrics: dict | None
    timings: dict

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    def up_direction(self) -> np.ndarray | None:
        """The world's up: opposite gravity (scene.json / params.json), else the camera's image-up, else None."""
        return up_direction((self.scene_info.get("gravity"), self.params.get("gravity")), self.camera)

    def material_path(self, name: str) -> Path | None:
        p = self.folder / "material" / name
        return p if p.exists() else None


def _read_json_opt(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SaftInputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SaftInputError(path, "expected a JSON object at the top level")
    return data


def read_result(result_dir: str | Path) -> Result:
    folder = Path(result_dir)
    if not folder.is_dir():
        raise SaftInputError(folder, "result folder not found")
    files = list_mesh_files(folder)
    first = read_obj(files[0])
    verts = [first.vertices]
    for f in files[1:]:
        m = read_obj(f)
        if m.quads.shape != first.quads.shape or not np.array_equal(m.quads, first.quads):
            raise SaftInputError(f, f"has another topology than {files[0].name}")
        verts.append(m.vertices)
    scene_info = _read_json_opt(folder / "scene.json")
    if not (folder / "params.json").is_file():
        raise SaftInputError(folder / "params.json", "missing: the result is incomplete (params.json is written "
                                                     "with the meshes); run the reconstruction again")
    params = _read_json_opt(folder / "params.json")
    camera = None
    if "camera" in scene_info:
        try:
            camera = Camera.from_json(scene_info["camera"])
        except (KeyError, TypeError, ValueError):
            raise SaftInputError(folder / "scene.json", "'camera' is not a camera (K, world_to_camera, width, "
                                                        "height)") from None
    texture = None
    if (folder / "texture.png").is_file():
        texture = read_image(folder / "texture.png")[:, :, :3]
    log_rows: list[dict] = []
    if (folder / "log.csv").is_file():
        with open(folder / "log.csv", newline="") as fh:
            log_rows = list(csv.DictReader(fh))
    config_text = (folder / "config.toml").read_text() if (folder / "config.toml").is_file() else None
    metrics = _read_json_opt(folder / "metrics.json") or None
    return Result(
        folder=folder, template=first, vertices=np.stack(verts),
        frame_dt=float(scene_info.get("frame_dt", params.get("frame_dt", 0.02))), texture=texture,
        params=params, camera=camera, scene_info=scene_info, config_text=config_text, log_rows=log_rows,
        metrics=metrics, timings=_read_json_opt(folder / "timings.json"),
    )


def read_config_dict(result_dir: str | Path) -> dict:
    path = Path(result_dir) / "config.toml"
    return tomllib.loads(path.read_text()) if path.is_file() else {}
