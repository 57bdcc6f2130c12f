"""The R1 template against the R1 ground truth (read from ../shared; skipped when it is absent)."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest

from saft.evaluate import (
    CD1, CD2, P2S_L1, GroundTruthSpec, evaluate_result_dir, evaluate_sequence, format_metrics_table,
    load_ground_truth_frames, read_point_cloud,
)
from saft.evaluate.ground_truth import ground_truth_files
from saft.scene.camera import Camera
from saft.scene.mesh import read_obj

# The template frame is the OpenCV camera frame rotated 180° about the optical axis (phi_sft/README.md).
R1_WORLD_TO_CAMERA = np.diag([-1.0, -1.0, 1.0, 1.0])


def _r1_spec(gt_dir) -> GroundTruthSpec:
    camera = Camera(np.array([[971.522, 0, 962.134], [0, 944.575, 554.778], [0, 0, 1]]), R1_WORLD_TO_CAMERA,
                    1920, 1080)
    return GroundTruthSpec.in_camera_frame(gt_dir, camera)


def test_r1_template_against_frame_0(r1_data):
    template = read_obj(r1_data["template"])
    first = ground_truth_files(_r1_spec(r1_data["gt_dir"]))[0]
    gt = read_point_cloud(first) * [-1.0, -1.0, 1.0]  # what the spec's camera_to_world must do
    np.testing.assert_allclose(load_ground_truth_frames(_r1_spec(r1_data["gt_dir"]))[0], gt)
    m = evaluate_sequence([template], None, [gt], seed=0)
    print("\nR1 template vs GT frame 0:", {k: round(v, 4) for k, v in m["mean"].items()})
    assert m["per_frame"][CD2][0] < 1.0  # 1e-4 m²
    assert m["per_frame"][P2S_L1][0] < 5.0  # mm
    # without taking the GT to the template frame it is ~0.57 m off
    wrong = evaluate_sequence([template], None, [gt * [-1.0, -1.0, 1.0]], seed=0)
    assert wrong["per_frame"][CD2][0] > 1000.0


@pytest.mark.slow
def test_r1_static_template_all_frames(r1_data, tmp_path):
    """The "static template" baseline over all 50 frames via a result folder; prints the time."""
    meshes = tmp_path / "result" / "meshes"
    meshes.mkdir(parents=True)
    n = len(ground_truth_files(_r1_spec(r1_data["gt_dir"])))
    for i in range(n):
        shutil.copyfile(r1_data["template"], meshes / f"frame_{i:03d}.obj")
    t0 = time.perf_counter()
    metrics = evaluate_result_dir(tmp_path / "result", _r1_spec(r1_data["gt_dir"]))
    elapsed = time.perf_counter() - t0
    print("\n" + format_metrics_table(metrics))
    print(f"evaluated {n} R1 frames in {elapsed:.1f} s (target: well under 60 s)")
    assert (tmp_path / "result" / "metrics.json").is_file()
    assert metrics["num_frames"] == n == 50
    assert metrics["per_frame"][CD2][0] < 1.0
    assert metrics["mean"][CD2] > metrics["per_frame"][CD2][0]  # the cloth moves away from its first shape
    assert metrics["mean"][CD1] > 0
