"""saft.evaluate: geometry metrics of a reconstruction against per-frame ground-truth point clouds.

Public API
----------
Ground truth (``ground_truth.py``)
    ``GroundTruthSpec(directory, frame="world" | "camera", flip_axes=None | "xy" | ..., camera_to_world=None)``
        ``GroundTruthSpec.in_camera_frame(directory, camera)`` for clouds in the OpenCV frame of a
        ``saft.scene.camera.Camera`` (the φ-SfT R1 ground truth: camera_to_world = diag(-1, -1, 1)).
    ``load_ground_truth_frames(spec) -> list[np.ndarray]``  (N_i, 3) float64 per frame, world frame, metres;
        files ``.pt``/``.pth`` (torch tensor N×3), ``.npy``, ``.ply``, sorted by name (numbers as numbers).
    ``ground_truth_files(spec) -> list[Path]``, ``read_point_cloud(path) -> np.ndarray`` (as stored).

Metrics (``metrics.py``), per frame, definitions of ``shared/data/phi_sft/README.md``
    ``frame_metrics(vertices, triangles, gt_points, rng) -> dict`` with keys
        ``cd2_1e-4m2``  L2 Chamfer, both directions summed (mesh sampled with as many points as the GT has)
        ``cd1_cm``      L1 Chamfer
        ``p2s_l1_mm``   mean distance GT point -> closest point of the mesh surface (exact)
        ``p2s_l2_1e-4m2``  mean squared distance of the same
        ``p2s_sym_l1_mm``, ``p2s_sym_l2_1e-4m2``  the paper's symmetric p2s: the above + mesh samples -> GT
        ``num_gt_points``
    ``sample_surface(vertices, triangles, count, rng)``, ``closest_points_on_mesh(vertices, triangles, points)``,
    ``point_to_surface_distances(...)``, ``nearest_neighbor_distances(source, target)``,
    ``frame_rng(seed, frame_index)``,
    ``depth_error(depth_rendered, depth_gt, roi=None) -> float`` (m; mean |ΔD| over pixels valid in both),
    ``depth_error_cm(...)``.

Sequences (``evaluate.py``)
    ``evaluate_sequence(meshes, triangles, gt_frames, seed=0, depth_pairs=None) -> dict``
        {"num_frames", "seed", "units", "definitions", "per_frame": {key: [..]}, "mean": {key: float}}
    ``evaluate_result_dir(result_dir, gt_spec, seed=0, allow_partial=False, write=True) -> dict``
        reads ``result_dir/meshes/*.obj`` (sorted), requires as many meshes as GT frames unless
        allow_partial (then the common prefix, with a warning), writes ``result_dir/metrics.json``; when
        ``result_dir/scene.json`` names the working camera it adds the depth error δ and writes
        ``result_dir/depth/frame_*.npz``.

Depth maps from point clouds (``depth_maps.py``)
    ``depth_pairs(meshes, gt_frames, camera)`` (rendered, ground truth) depth maps on one pixel grid:
    ``mesh_depth`` rasterizes the mesh, ``point_cloud_depth`` projects the cloud (nearest point per pixel),
    ``depth_camera`` resizes the camera to about two cloud points per pixel.
    ``format_metrics_table(metrics) -> str``  per-frame rows and a mean row.

Scenes (``scene_gt.py``)
    ``ground_truth_spec_for(scene, path=None, frame=None, flip_axes=None)`` the scene's own ground truth
        (camera-frame clouds taken to the world frame with the scene's camera);
    ``ground_truth_spec_from_path(path, frame=None, flip_axes=None, root=None)`` for ``saft evaluate --gt``;
    ``evaluate_static_template(scene, spec)`` the baseline; ``format_comparison_table({name: metrics})``.

Input problems (missing folder, no files, wrong shapes, unreadable files, count mismatch) raise
``saft.errors.SaftInputError`` naming the file or folder.
"""

from saft.evaluate.evaluate import (
    METRIC_LABELS,
    METRICS_FILENAME,
    evaluate_result_dir,
    evaluate_sequence,
    format_metrics_table,
)
from saft.evaluate.ground_truth import (
    GroundTruthSpec,
    ground_truth_files,
    load_ground_truth_frames,
    read_point_cloud,
)
from saft.evaluate.metrics import (
    CD1,
    CD2,
    DEPTH,
    METRIC_KEYS,
    NUM_POINTS,
    P2S_L1,
    P2S_L2,
    P2S_SYM_L1,
    P2S_SYM_L2,
    closest_points_on_mesh,
    depth_error,
    depth_error_cm,
    frame_metrics,
    frame_rng,
    nearest_neighbor_distances,
    point_to_surface_distances,
    sample_surface,
)

__all__ = [
    "CD1", "CD2", "DEPTH", "METRIC_KEYS", "METRIC_LABELS", "METRICS_FILENAME", "NUM_POINTS", "P2S_L1", "P2S_L2", "P2S_SYM_L1",
    "P2S_SYM_L2", "GroundTruthSpec", "closest_points_on_mesh", "depth_error", "depth_error_cm",
    "evaluate_result_dir", "evaluate_sequence", "format_metrics_table", "frame_metrics", "frame_rng",
    "ground_truth_files", "load_ground_truth_frames", "nearest_neighbor_distances",
    "point_to_surface_distances", "read_point_cloud", "sample_surface", "evaluate_static_template",
    "format_comparison_table", "ground_truth_spec_for", "ground_truth_spec_from_path",
]
from saft.evaluate.scene_gt import (
    evaluate_static_template,
    format_comparison_table,
    ground_truth_spec_for,
    ground_truth_spec_from_path,
)
