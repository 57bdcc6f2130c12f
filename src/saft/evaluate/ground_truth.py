"""Ground-truth point clouds for evaluation: one file per frame, converted once into the world frame.

Supported files (all in one folder, one kind of file per folder, sorted by name with numbers compared as
numbers, so ``pc_2`` comes before ``pc_10``):

* ``.pt`` / ``.pth``: a torch tensor (or a numpy array) N×3, metres;
* ``.npy``: a numpy array N×3, metres;
* ``.ply``: a point cloud (or a mesh, whose vertices are taken), read with trimesh.

Conversion into the world (template) frame, in this order: first negate the axes named in ``flip_axes``
(e.g. "xy"), then, when ``frame == "camera"``, apply ``camera_to_world``. Points that are not finite
(holes of a depth sensor) are dropped.

The φ-SfT R1 ground truth is stored in the OpenCV camera frame (x and y negated relative to the template
frame); ``GroundTruthSpec.in_camera_frame(directory, camera)`` with the scene's camera takes it to the
template frame (for R1 ``camera_to_world`` is diag(-1, -1, 1)), and so does
``GroundTruthSpec(directory, frame="world", flip_axes="xy")``.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from saft.errors import SaftInputError

POINT_CLOUD_SUFFIXES = (".pt", ".pth", ".npy", ".ply")


@dataclass(frozen=True)
class GroundTruthSpec:
    """Where the per-frame ground-truth point clouds are and which frame they are stored in.

    directory:       folder of per-frame point clouds (see the module docstring).
    frame:           "world" (already the scene's world/template frame, up to ``flip_axes``) or "camera"
                     (the OpenCV camera frame of the scene's camera; ``camera_to_world`` is then required).
    flip_axes:       axes to negate first, any of "x", "y", "z" (e.g. "xy"); None or "" for none.
    camera_to_world: 4×4 rigid transform, required when frame == "camera".
    """

    directory: str | Path
    frame: Literal["world", "camera"] = "world"
    flip_axes: str | None = None
    camera_to_world: np.ndarray | None = None

    @staticmethod
    def in_camera_frame(directory: str | Path, camera, flip_axes: str | None = None) -> "GroundTruthSpec":
        """Ground truth stored in the OpenCV frame of `camera` (a ``saft.scene.camera.Camera``)."""
        return GroundTruthSpec(directory, "camera", flip_axes, np.asarray(camera.camera_to_world, dtype=np.float64))

    def transform(self) -> np.ndarray:
        """The 4×4 matrix taking stored points to the world frame (flip, then camera_to_world).

        Raises SaftInputError (naming the directory) when the spec is inconsistent.
        """
        where = self.directory
        flip = np.ones(3)
        for axis in (self.flip_axes or "").lower():
            if axis not in "xyz":
                raise SaftInputError(where, f"flip_axes must use the letters x, y, z only, got {self.flip_axes!r}")
            flip["xyz".index(axis)] = -1.0
        M = np.diag([*flip, 1.0])
        if self.frame == "world":
            if self.camera_to_world is not None:
                raise SaftInputError(where, 'camera_to_world is given but frame is "world"; use frame="camera"')
            return M
        if self.frame != "camera":
            raise SaftInputError(where, f'ground-truth frame must be "world" or "camera", got {self.frame!r}')
        if self.camera_to_world is None:
            raise SaftInputError(where, 'ground truth in the "camera" frame needs camera_to_world (4x4)')
        T = np.asarray(self.camera_to_world, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise SaftInputError(where, f"camera_to_world must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if (not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or abs(np.linalg.det(R) - 1.0) > 1e-4
                or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-8)):
            raise SaftInputError(where, "camera_to_world is not a rigid transform (rotation + translation)")
        return T @ M


def _natural_key(path: Path):
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def ground_truth_files(spec: GroundTruthSpec | str | Path) -> list[Path]:
    """The per-frame point-cloud files of the spec's directory, in frame order."""
    directory = Path(spec.directory if isinstance(spec, GroundTruthSpec) else spec)
    if not directory.exists():
        raise SaftInputError(directory, "ground-truth folder not found")
    if not directory.is_dir():
        raise SaftInputError(directory, "ground truth must be a folder of per-frame point clouds")
    files = [p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in POINT_CLOUD_SUFFIXES]
    if not files:
        raise SaftInputError(
            directory, f"no ground-truth point clouds ({', '.join(POINT_CLOUD_SUFFIXES)}) in the folder")
    kinds = sorted({".pt" if p.suffix.lower() == ".pth" else p.suffix.lower() for p in files})
    if len(kinds) > 1:
        raise SaftInputError(directory, f"the folder mixes point-cloud formats ({', '.join(kinds)}); keep one")
    return sorted(files, key=_natural_key)


def read_point_cloud(path: str | Path) -> np.ndarray:
    """One point cloud file as it is stored: (N, 3) float64 (non-finite points dropped)."""
    path = Path(path)
    if not path.is_file():
        raise SaftInputError(path, "point cloud not found")
    suffix = path.suffix.lower()
    try:
        if suffix in (".pt", ".pth"):
            import torch

            data = torch.load(path, map_location="cpu", weights_only=True)
            if isinstance(data, torch.Tensor):
                data = data.detach().to(torch.float64).numpy()
        elif suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        elif suffix == ".ply":
            import trimesh

            loaded = trimesh.load(path, process=False)
            data = getattr(loaded, "vertices", None)
            if data is None:
                raise ValueError(f"not a point cloud or mesh ({type(loaded).__name__})")
        else:
            raise SaftInputError(path, f"unsupported point-cloud format {suffix!r} (use .pt, .npy or .ply)")
    except SaftInputError:
        raise
    except Exception as exc:  # torch, numpy and trimesh raise many kinds of errors for corrupt files
        raise SaftInputError(path, f"cannot read the point cloud ({type(exc).__name__}: {exc})".splitlines()[0]) from None
    if not isinstance(data, np.ndarray):
        raise SaftInputError(path, f"expected an N x 3 array of points, found a {type(data).__name__}")
    if data.ndim != 2 or data.shape[1] != 3:
        raise SaftInputError(path, f"expected an N x 3 array of points, got shape {tuple(data.shape)}")
    if not np.issubdtype(data.dtype, np.number):
        raise SaftInputError(path, f"expected numbers, got dtype {data.dtype}")
    points = np.asarray(data, dtype=np.float64)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        warnings.warn(f"{path}: dropped {int((~finite).sum())} non-finite points", stacklevel=2)
        points = points[finite]
    if len(points) == 0:
        raise SaftInputError(path, "the point cloud has no (finite) points")
    return points


def load_ground_truth_frames(spec: GroundTruthSpec) -> list[np.ndarray]:
    """Read every frame's point cloud, in frame order, converted into the world (template) frame."""
    T = spec.transform()
    frames = []
    for path in ground_truth_files(spec):
        pts = read_point_cloud(path)
        frames.append(pts @ T[:3, :3].T + T[:3, 3])
    return frames
