"""Ground-truth readers (.pt/.npy/.ply, flips, camera frame), result folders, metrics.json, bad input."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
import trimesh

from saft.errors import SaftInputError
from saft.evaluate import (
    CD2, METRIC_KEYS, GroundTruthSpec, evaluate_result_dir, format_metrics_table, ground_truth_files,
    load_ground_truth_frames,
)
from saft.scene.camera import Camera
from saft.scene.mesh import QuadMesh, write_obj

PTS = np.array([[0.1, 0.2, 1.0], [-0.3, 0.4, 1.5], [0.0, 0.0, 2.0]])


def _quad_sheet(n: int = 5, size: float = 0.2, z: float = 1.0) -> QuadMesh:
    u = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(u, u, indexing="xy")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    quads = np.stack([a, a + 1, a + n + 1, a + n], axis=1)
    uvs = (v[:, :2] - v[:, :2].min(0)) / size
    return QuadMesh(v, quads, uvs)


# ---------------------------------------------------------------- readers
@pytest.mark.parametrize("kind", ["pt", "npy", "ply"])
def test_reads_each_format_in_natural_order(tmp_path, kind):
    for k in (10, 2, 1):  # natural order: 1, 2, 10
        pts = PTS + k
        path = tmp_path / f"cloud_{k}.{kind}"
        if kind == "pt":
            torch.save(torch.tensor(pts, dtype=torch.float32), path)
        elif kind == "npy":
            np.save(path, pts)
        else:
            trimesh.PointCloud(pts).export(path)
    frames = load_ground_truth_frames(GroundTruthSpec(tmp_path))
    assert [p.name for p in ground_truth_files(GroundTruthSpec(tmp_path))] == [
        f"cloud_{k}.{kind}" for k in (1, 2, 10)]
    for k, f in zip((1, 2, 10), frames):
        assert f.dtype == np.float64 and f.shape == (3, 3)
        np.testing.assert_allclose(f, PTS + k, atol=1e-6)


def test_flip_and_camera_frame(tmp_path):
    np.save(tmp_path / "f0.npy", PTS)
    flipped = load_ground_truth_frames(GroundTruthSpec(tmp_path, flip_axes="xy"))[0]
    np.testing.assert_allclose(flipped, PTS * [-1, -1, 1])
    # camera frame: world = camera_to_world · p (here a rotation about z by 90° and a translation)
    c2w = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    world = load_ground_truth_frames(GroundTruthSpec(tmp_path, "camera", camera_to_world=c2w))[0]
    np.testing.assert_allclose(world, PTS @ c2w[:3, :3].T + c2w[:3, 3])
    # the R1 convention: the OpenCV camera of the template frame has camera_to_world = diag(-1, -1, 1)
    cam = Camera(np.eye(3), np.diag([-1.0, -1.0, 1.0, 1.0]), 10, 10)
    via_cam = load_ground_truth_frames(GroundTruthSpec.in_camera_frame(tmp_path, cam))[0]
    np.testing.assert_allclose(via_cam, flipped)


def test_non_finite_points_are_dropped_with_a_warning(tmp_path):
    np.save(tmp_path / "f0.npy", np.concatenate([PTS, [[np.nan, 0, 1]]]))
    with pytest.warns(UserWarning, match="dropped 1 non-finite"):
        frames = load_ground_truth_frames(GroundTruthSpec(tmp_path))
    assert frames[0].shape == (3, 3)


# ---------------------------------------------------------------- bad ground truth
def _raises_naming(path, match, fn, *args, **kwargs):
    with pytest.raises(SaftInputError, match=match) as info:
        fn(*args, **kwargs)
    assert str(path) in str(info.value), str(info.value)
    assert "\n" not in str(info.value)


def test_missing_and_empty_folders(tmp_path):
    _raises_naming(tmp_path / "nope", "not found", load_ground_truth_frames, GroundTruthSpec(tmp_path / "nope"))
    (tmp_path / "readme.txt").write_text("no clouds here")
    _raises_naming(tmp_path, "no ground-truth point clouds", load_ground_truth_frames, GroundTruthSpec(tmp_path))
    _raises_naming(tmp_path / "readme.txt", "must be a folder", load_ground_truth_frames,
                   GroundTruthSpec(tmp_path / "readme.txt"))


@pytest.mark.parametrize(
    "name, write, match",
    [
        ("bad.npy", lambda p: np.save(p, np.zeros((5, 2))), r"N x 3.*\(5, 2\)"),
        ("bad.npy", lambda p: np.save(p, np.zeros((0, 3))), "no \\(finite\\) points"),
        ("bad.npy", lambda p: p.write_bytes(b"not numpy"), "cannot read"),
        ("bad.pt", lambda p: torch.save(torch.zeros(4, 3, 2), p), r"N x 3.*\(4, 3, 2\)"),
        ("bad.pt", lambda p: torch.save({"points": torch.zeros(4, 3)}, p), "found a dict"),
        ("bad.pt", lambda p: p.write_bytes(b"\x00garbage"), "cannot read"),
        ("bad.ply", lambda p: p.write_text("ply\nformat nonsense\n"), "cannot read"),
    ],
)
def test_bad_point_cloud_files_name_the_file(tmp_path, name, write, match):
    path = tmp_path / name
    write(path)
    _raises_naming(path, match, load_ground_truth_frames, GroundTruthSpec(tmp_path))


def test_mixed_formats_and_bad_specs(tmp_path):
    np.save(tmp_path / "a.npy", PTS)
    torch.save(torch.tensor(PTS), tmp_path / "b.pt")
    _raises_naming(tmp_path, "mixes point-cloud formats", load_ground_truth_frames, GroundTruthSpec(tmp_path))
    (tmp_path / "b.pt").unlink()
    _raises_naming(tmp_path, "needs camera_to_world", load_ground_truth_frames, GroundTruthSpec(tmp_path, "camera"))
    _raises_naming(tmp_path, "flip_axes", load_ground_truth_frames, GroundTruthSpec(tmp_path, flip_axes="xw"))
    _raises_naming(tmp_path, "not a rigid transform", load_ground_truth_frames,
                   GroundTruthSpec(tmp_path, "camera", camera_to_world=np.diag([2.0, 1, 1, 1])))
    _raises_naming(tmp_path, '"world" or "camera"', load_ground_truth_frames, GroundTruthSpec(tmp_path, "cam"))


# ---------------------------------------------------------------- result folders
def _result_dir(tmp_path, n_meshes, n_gt, offset=0.005):
    mesh = _quad_sheet()
    res, gt = tmp_path / "result", tmp_path / "gt"
    (res / "meshes").mkdir(parents=True)
    gt.mkdir()
    for i in range(n_meshes):
        write_obj(res / "meshes" / f"frame_{i:03d}.obj", mesh)
    rng = np.random.default_rng(0)
    for i in range(n_gt):
        pts = np.concatenate([rng.uniform(-0.1, 0.1, (500, 2)), np.full((500, 1), 1.0 + offset)], axis=1)
        np.save(gt / f"point_cloud_{i:03d}.npy", pts)
    return res, gt


def test_result_dir_writes_metrics_json_and_table(tmp_path):
    res, gt = _result_dir(tmp_path, 3, 3)
    metrics = evaluate_result_dir(res, GroundTruthSpec(gt))
    on_disk = json.loads((res / "metrics.json").read_text())
    assert on_disk["num_frames"] == 3
    assert set(METRIC_KEYS) <= set(on_disk["mean"]) and set(METRIC_KEYS) <= set(on_disk["per_frame"])
    assert on_disk["per_frame"][CD2] == pytest.approx(metrics["per_frame"][CD2])
    assert on_disk["mesh_files"] == ["frame_000.obj", "frame_001.obj", "frame_002.obj"]
    assert metrics["mean"]["p2s_l1_mm"] == pytest.approx(5.0)  # GT 5 mm above the sheet's interior
    table = format_metrics_table(metrics)
    lines = table.splitlines()
    assert "CD2 [1e-4 m²]" in lines[0] and lines[-1].startswith("mean")
    assert sum(line.startswith("frame_") for line in lines) == 3


def test_result_dir_with_a_camera_gets_the_depth_error_and_depth_maps(tmp_path):
    """scene.json names the working camera: the clouds and the meshes become depth maps on one grid."""
    from saft.result import list_depth_files, read_depth_pair

    res, gt = _result_dir(tmp_path, 2, 2, offset=0.005)     # GT plane 5 mm behind the sheet, facing the camera
    assert "depth_cm" not in evaluate_result_dir(res, GroundTruthSpec(gt), write=False)["mean"]
    camera = Camera.from_intrinsics(200.0, 200.0, 49.5, 49.5, np.eye(4), 100, 100)
    (res / "scene.json").write_text(json.dumps({"camera": camera.to_json()}))
    metrics = evaluate_result_dir(res, GroundTruthSpec(gt))
    assert metrics["per_frame"]["depth_cm"] == pytest.approx([0.5, 0.5], abs=1e-3)
    files = list_depth_files(res)
    assert [f.name for f in files] == ["frame_000.npz", "frame_001.npz"]
    rendered, target = read_depth_pair(files[0])
    both = np.isfinite(rendered) & np.isfinite(target)
    assert both.sum() > 100                                   # dense: about two cloud points per pixel
    assert np.allclose(rendered[both], 1.0, atol=1e-5) and np.allclose(target[both], 1.005, atol=1e-9)


def test_result_dir_frame_counts(tmp_path):
    res, gt = _result_dir(tmp_path, 2, 3)
    _raises_naming(res / "meshes", "2 meshes but 3 ground-truth frames", evaluate_result_dir, res,
                   GroundTruthSpec(gt))
    assert not (res / "metrics.json").exists()
    with pytest.warns(UserWarning, match="evaluating the first 2"):
        metrics = evaluate_result_dir(res, GroundTruthSpec(gt), allow_partial=True)
    assert metrics["num_frames"] == 2 and len(metrics["ground_truth_files"]) == 2


def test_result_dir_bad_input(tmp_path):
    _raises_naming(tmp_path / "none", "result folder not found", evaluate_result_dir, tmp_path / "none",
                   GroundTruthSpec(tmp_path))
    res, gt = _result_dir(tmp_path, 1, 1)
    (res / "meshes" / "frame_000.obj").unlink()
    _raises_naming(res / "meshes", "no .obj meshes", evaluate_result_dir, res, GroundTruthSpec(gt))
    (res / "meshes").rmdir()
    _raises_naming(res / "meshes", "no meshes/ folder", evaluate_result_dir, res, GroundTruthSpec(gt))
    (res / "meshes").mkdir()
    (res / "meshes" / "frame_000.obj").write_text("v 0 0 0\nf 1 2 3 4\n")
    _raises_naming(res / "meshes" / "frame_000.obj", "vertex that does not exist", evaluate_result_dir, res, GroundTruthSpec(gt))


def test_result_dir_accepts_triangle_meshes_without_uvs(tmp_path):
    """Meshes of other methods (triangles, no vt) are read with trimesh."""
    res, gt = _result_dir(tmp_path, 1, 1)
    quad = _quad_sheet()
    trimesh.Trimesh(quad.vertices, quad.triangles, process=False).export(res / "meshes" / "frame_000.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        metrics = evaluate_result_dir(res, GroundTruthSpec(gt), write=False)
    assert metrics["per_frame"]["p2s_l1_mm"][0] == pytest.approx(5.0)
