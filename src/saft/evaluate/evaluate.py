"""Evaluate a reconstructed mesh sequence against per-frame ground truth; write metrics.json; print a table."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from saft.errors import SaftInputError
from saft.evaluate.depth_maps import depth_pairs
from saft.evaluate.ground_truth import GroundTruthSpec, ground_truth_files, load_ground_truth_frames
from saft.evaluate.metrics import (CD1, CD2, DEPTH, METRIC_KEYS, NUM_POINTS, P2S_L1, P2S_L2, P2S_SYM_L1, P2S_SYM_L2,
                                   depth_error_cm, frame_metrics, frame_rng)
from saft.io_utils import atomic_write_json
from saft.result import check_frame_numbers, write_depth_pair
from saft.scene.camera import Camera
from saft.scene.mesh import QuadMesh, read_obj

METRICS_FILENAME = "metrics.json"

UNITS = {
    CD2: "1e-4 m^2", CD1: "cm", P2S_L1: "mm", P2S_L2: "1e-4 m^2", P2S_SYM_L1: "mm", P2S_SYM_L2: "1e-4 m^2",
    DEPTH: "cm",
}
# readable names with their units, for tables and figures people read (report, viewer, batch summary)
METRIC_LABELS = {
    CD2: "CD2 (10⁻⁴ m²)", CD1: "CD1 (cm)", P2S_L1: "p2s (mm)", P2S_L2: "p2s L2 (10⁻⁴ m²)",
    P2S_SYM_L1: "symmetric p2s (mm)", P2S_SYM_L2: "symmetric p2s L2 (10⁻⁴ m²)", DEPTH: "depth δ (cm)",
}
DEFINITIONS = {
    CD2: "mean sq. NN distance GT->mesh samples + mean sq. NN distance samples->GT (summed)",
    CD1: "as cd2 with unsquared distances",
    P2S_L1: "mean distance from GT points to the closest point of the mesh surface",
    P2S_L2: "mean squared distance from GT points to the closest point of the mesh surface",
    P2S_SYM_L1: "p2s_l1 + mean distance from mesh samples to the nearest GT point (paper's symmetric p2s)",
    P2S_SYM_L2: "p2s_l2 + mean squared distance from mesh samples to the nearest GT point",
    DEPTH: "mean |D_rendered - D_gt| over pixels valid in both depth maps",
}


def _mesh_arrays(mesh, triangles) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(mesh, QuadMesh):
        return mesh.vertices, (mesh.triangles if triangles is None else np.asarray(triangles))
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):  # a trimesh.Trimesh
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces if triangles is None else triangles)
    if isinstance(mesh, tuple) and len(mesh) == 2:  # (vertices, triangles)
        return np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1])
    if triangles is None:
        raise ValueError("triangles are required when meshes are given as vertex arrays")
    return np.asarray(mesh, dtype=np.float64).reshape(-1, 3), np.asarray(triangles)


def evaluate_sequence(meshes: Sequence, triangles: np.ndarray | None, gt_frames: Sequence[np.ndarray],
                      seed: int = 0, depth_pairs: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> dict:
    """Per-frame and mean metrics of a mesh sequence against ground-truth point clouds.

    meshes:      one per frame: (V, 3) vertex arrays (then `triangles` (T, 3) is required), QuadMesh,
                 trimesh.Trimesh, or (vertices, triangles) pairs. Same frame and unit (m) as `gt_frames`.
    triangles:   (T, 3) vertex indices shared by all frames, or None (taken from each mesh).
    gt_frames:   (N_i, 3) ground-truth point clouds, world frame, metres (see load_ground_truth_frames).
    seed:        frame i samples its mesh with numpy.random.default_rng([seed, i]): numbers repeat.
    depth_pairs: optional (rendered, ground truth) depth maps per frame (metres); adds "depth_cm".

    Returns {"num_frames", "seed", "units", "definitions", "per_frame": {key: [value per frame]},
    "mean": {key: mean over frames}}; keys carry their unit ("cd2_1e-4m2", "cd1_cm", "p2s_l1_mm", ...).
    """
    if len(meshes) != len(gt_frames):
        raise ValueError(f"{len(meshes)} meshes but {len(gt_frames)} ground-truth frames")
    if depth_pairs is not None and len(depth_pairs) != len(meshes):
        raise ValueError(f"{len(depth_pairs)} depth pairs but {len(meshes)} meshes")
    keys = list(METRIC_KEYS) + [NUM_POINTS]
    per_frame: dict[str, list] = {k: [] for k in keys}
    for i, (mesh, gt) in enumerate(zip(meshes, gt_frames)):
        vertices, tris = _mesh_arrays(mesh, triangles)
        row = frame_metrics(vertices, tris, gt, frame_rng(seed, i))
        for k in keys:
            per_frame[k].append(row[k])
    if depth_pairs is not None:
        per_frame[DEPTH] = [depth_error_cm(rendered, gt) for rendered, gt in depth_pairs]
    mean = {}
    for k, values in per_frame.items():
        finite = [v for v in values if not (isinstance(v, float) and math.isnan(v))]
        mean[k] = float(np.mean(finite)) if finite else float("nan")
    return {
        "num_frames": len(meshes),
        "seed": int(seed),
        "units": {k: UNITS[k] for k in per_frame if k in UNITS},
        "definitions": {k: DEFINITIONS[k] for k in per_frame if k in DEFINITIONS},
        "per_frame": per_frame,
        "mean": mean,
    }


def _natural_key(path: Path):
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def read_result_mesh(path: Path):
    """A result mesh: saft's own quad OBJ, or any triangle/polygon mesh trimesh can read (other methods)."""
    try:
        return read_obj(path)
    except SaftInputError as quad_error:
        if not path.is_file():
            raise
        try:
            import trimesh

            mesh = trimesh.load(path, force="mesh", process=False)
            if len(mesh.faces) == 0:
                raise ValueError("no faces")
            return mesh
        except Exception:
            raise quad_error from None


def evaluate_result_dir(result_dir: str | Path, gt_spec: GroundTruthSpec, seed: int = 0,
                        allow_partial: bool = False, write: bool = True) -> dict:
    """Evaluate `result_dir/meshes/*.obj` (frame order = sorted names) against the ground truth.

    The number of meshes must equal the number of ground-truth frames; with allow_partial=True the common
    prefix is evaluated instead, with a warning. Writes `result_dir/metrics.json` atomically (unless
    write=False) and returns the same dict as evaluate_sequence plus "result_dir", "mesh_files",
    "ground_truth_dir", "ground_truth_files". Every input problem raises SaftInputError naming the path.
    """
    result_dir = Path(result_dir)
    if not result_dir.is_dir():
        raise SaftInputError(result_dir, "result folder not found")
    mesh_dir = result_dir / "meshes"
    if not mesh_dir.is_dir():
        raise SaftInputError(mesh_dir, "no meshes/ folder in the result folder (expected meshes/frame_000.obj ...)")
    mesh_files = sorted((p for p in mesh_dir.iterdir() if p.is_file() and p.suffix.lower() == ".obj"),
                        key=_natural_key)
    if not mesh_files:
        raise SaftInputError(mesh_dir, "no .obj meshes in the folder")
    if all(p.stem.startswith("frame_") for p in mesh_files):   # saft's own naming: no frame may be missing
        mesh_files = check_frame_numbers(mesh_files, result_dir)
    gt_files = ground_truth_files(gt_spec)
    if len(mesh_files) != len(gt_files):
        problem = (f"{len(mesh_files)} meshes but {len(gt_files)} ground-truth frames in {gt_spec.directory}")
        if not allow_partial:
            raise SaftInputError(mesh_dir, problem + " (allow_partial evaluates the common prefix)")
        warnings.warn(f"{mesh_dir}: {problem}; evaluating the first {min(len(mesh_files), len(gt_files))}",
                      stacklevel=2)
    n = min(len(mesh_files), len(gt_files))
    mesh_files = mesh_files[:n]
    gt_frames = load_ground_truth_frames(gt_spec)[:n]
    meshes = [read_result_mesh(p) for p in mesh_files]
    pairs = _depth_pairs_from_clouds(result_dir, meshes, gt_frames)
    metrics = evaluate_sequence(meshes, None, gt_frames, seed=seed, depth_pairs=pairs)
    metrics = {
        "result_dir": str(result_dir),
        "ground_truth_dir": str(gt_spec.directory),
        **metrics,
        "mesh_files": [p.name for p in mesh_files],
        "ground_truth_files": [p.name for p in gt_files[:n]],
    }
    if write:
        for i, (rendered, target) in enumerate(pairs or []):
            write_depth_pair(result_dir, i, rendered, target)
        atomic_write_json(result_dir / METRICS_FILENAME, _json_safe(metrics))
    return metrics


def _depth_pairs_from_clouds(result_dir: Path, meshes: list, gt_frames: list[np.ndarray]):
    """Depth maps of the meshes and of the clouds in the result's working camera (saft.evaluate.depth_maps),
    or None when the result folder does not say its camera (meshes of another method)."""
    import json

    info = result_dir / "scene.json"
    try:
        camera = Camera.from_json(json.loads(info.read_text())["camera"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return depth_pairs([_mesh_arrays(m, None) for m in meshes], gt_frames, camera)


def _json_safe(obj):
    """NaN is not JSON: write it as null."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


_COLUMNS = (
    (CD2, "CD2 [1e-4 m²]", "{:.3f}"),
    (CD1, "CD1 [cm]", "{:.3f}"),
    (P2S_L1, "p2s L1 [mm]", "{:.2f}"),
    (P2S_L2, "p2s L2 [1e-4 m²]", "{:.3f}"),
    (P2S_SYM_L1, "p2s-sym L1 [mm]", "{:.2f}"),
    (P2S_SYM_L2, "p2s-sym L2 [1e-4 m²]", "{:.3f}"),
    (DEPTH, "depth [cm]", "{:.3f}"),
)


def format_metrics_table(metrics: dict) -> str:
    """Plain-text table: one row per frame, then the mean row (columns present in the metrics only)."""
    per_frame = metrics["per_frame"]
    cols = [c for c in _COLUMNS if c[0] in per_frame]
    names = metrics.get("mesh_files") or [str(i) for i in range(metrics["num_frames"])]

    def fmt(fmt_str, v):
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt_str.format(v)

    header = ["frame"] + [c[1] for c in cols]
    rows = [[str(names[i])] + [fmt(c[2], per_frame[c[0]][i]) for c in cols] for i in range(metrics["num_frames"])]
    mean_row = ["mean"] + [fmt(c[2], metrics["mean"][c[0]]) for c in cols]
    widths = [max(len(r[j]) for r in [header, *rows, mean_row]) for j in range(len(header))]

    def line(r):
        return "  ".join(r[0].ljust(widths[0]) if j == 0 else r[j].rjust(widths[j]) for j in range(len(r)))

    sep = "-" * len(line(header))
    return "\n".join([line(header), sep, *(line(r) for r in rows), sep, line(mean_row)])
