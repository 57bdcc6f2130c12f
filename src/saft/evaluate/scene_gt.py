"""Ground truth as a scene names it, the static-template baseline, and a comparison table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saft.errors import SaftInputError
from saft.evaluate.depth_maps import depth_pairs
from saft.evaluate.evaluate import _COLUMNS, evaluate_sequence
from saft.evaluate.ground_truth import GroundTruthSpec, load_ground_truth_frames
from saft.scene import load_scene


def ground_truth_spec_for(scene, path: str | Path | None = None, *, frame: str | None = None,
                          flip_axes: str | None = None, root=None) -> GroundTruthSpec:
    """The ground truth of `scene` (its own, or the folder `path`), in the scene's world frame.

    Clouds in the "camera" frame are taken to the world with the scene's camera, so the φ-SfT R1 ground
    truth (stored in the OpenCV camera frame) comes out in the template's frame without any flag.
    """
    directory = Path(path) if path is not None else scene.ground_truth_dir
    if directory is None:
        raise SaftInputError(scene.source, "this scene names no ground truth; pass --gt GT_DIR")
    frame = frame or (scene.ground_truth_frame if path is None else "world")
    if frame == "camera":
        return GroundTruthSpec.in_camera_frame(directory, scene.camera, flip_axes)
    return GroundTruthSpec(directory, "world", flip_axes)


def ground_truth_spec_from_path(path: str | Path, *, frame: str | None = None, flip_axes: str | None = None,
                                root=None) -> GroundTruthSpec:
    """`--gt` of `saft evaluate`: a folder of point clouds, or a scene (folder or .json) that names them."""
    path = Path(path)
    is_scene = path.suffix.lower() == ".json" or (path.is_dir() and (path / "template.obj").is_file())
    if is_scene:
        return ground_truth_spec_for(load_scene(path, root=root), None, frame=frame, flip_axes=flip_axes)
    if not path.exists():
        raise SaftInputError(path, "ground truth not found")
    return GroundTruthSpec(path, frame or "world", flip_axes)


def evaluate_static_template(scene, spec: GroundTruthSpec, seed: int = 0, frames: int | None = None) -> dict:
    """Metrics of the template left where it is in every frame (the baseline any method must beat)."""
    gt = load_ground_truth_frames(spec)
    if frames is not None:
        gt = gt[:frames]
    meshes = [scene.template.vertices] * len(gt)
    pairs = depth_pairs([(scene.template.vertices, scene.template.triangles)] * len(gt), gt, scene.working_camera())
    return evaluate_sequence(meshes, scene.template.triangles, gt, seed=seed, depth_pairs=pairs)


def format_comparison_table(results: dict[str, dict]) -> str:
    """Mean metrics of several methods side by side (rows: methods)."""
    keys = [c for c in _COLUMNS if all(c[0] in r["mean"] for r in results.values())]
    header = ["method"] + [c[1] for c in keys]
    rows = [[name] + [c[2].format(r["mean"][c[0]]) if np.isfinite(r["mean"][c[0]]) else "n/a" for c in keys]
            for name, r in results.items()]
    widths = [max(len(row[j]) for row in [header, *rows]) for j in range(len(header))]

    def line(r):
        return "  ".join(r[0].ljust(widths[0]) if j == 0 else r[j].rjust(widths[j]) for j in range(len(r)))

    return "\n".join([line(header), "-" * len(line(header)), *(line(r) for r in rows)])
