"""A run on a GPU machine (skipped without CUDA): `--device auto` splits the run (physics on the CPU,
renders on CUDA: saft.device.plan_devices) and `--device cuda` puts everything on the GPU; both
reconstruct the tiny scene as well as the CPU run does."""

import numpy as np
import pytest
import torch

from saft.config_io import load_config
from saft.evaluate import evaluate_result_dir, evaluate_static_template, ground_truth_spec_for
from saft.reconstruct import SaftConfig, reconstruct
from saft.result import read_result

from test_reconstruct_e2e import TINY_CONFIG, tiny_scene  # noqa: F401  (the fixture)

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs an NVIDIA GPU")]


@pytest.mark.parametrize("device", ["auto", "cuda"])
def test_gpu_run_matches_the_cpu_run(tiny_scene, tmp_path, device):  # noqa: F811
    spec = ground_truth_spec_for(tiny_scene)
    static = evaluate_static_template(tiny_scene, spec)["mean"]["cd2_1e-4m2"]
    verts = []
    for i, dev in enumerate(("cpu", device)):
        cfg = load_config(SaftConfig, None, [c for c in TINY_CONFIG if not c.startswith("run.device")]
                          + [f'run.device="{dev}"'])
        reconstruct(tiny_scene, cfg, tmp_path / f"run{i}", quiet=True)
        cd2 = evaluate_result_dir(tmp_path / f"run{i}", spec)["mean"]["cd2_1e-4m2"]
        assert cd2 <= 0.3 * static, f"{dev}: CD2 {cd2:.3f} against the static template's {static:.3f}"
        verts.append(read_result(tmp_path / f"run{i}").vertices)
    gt = np.load(tiny_scene.source / "gt_vertices.npy")
    motion = np.linalg.norm(gt - gt[:1], axis=-1).mean()
    assert np.linalg.norm(verts[0] - verts[1], axis=-1).mean() <= 0.2 * motion
