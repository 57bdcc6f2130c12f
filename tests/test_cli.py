"""The `saft` command: help texts, evaluate end to end, one-line errors."""

import subprocess
import sys

import numpy as np
import pytest

from saft.cli import main
from saft.result import mesh_path
from saft.scene import write_obj
from saft.synthetic.hanging_cloth import grid_template


def test_help_texts():
    for argv in (["--help"], ["evaluate", "--help"], ["reconstruct", "--help"], ["demo", "--help"]):
        r = subprocess.run([sys.executable, "-m", "saft", *argv], capture_output=True, text=True)
        assert r.returncode == 0 and "usage: saft" in r.stdout, r.stderr


def test_evaluate_prints_a_table_and_writes_metrics(tmp_path, capsys):
    mesh = grid_template(6, 0.3)
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        verts = mesh.vertices + [0, 0, 0.01 * i]
        write_obj(mesh_path(tmp_path / "res", i), mesh, verts)
        pts = mesh.vertices[rng.integers(0, mesh.num_vertices, 500)]
        np.save(gt_dir / f"frame_{i:03d}.npy", pts)
    assert main(["evaluate", str(tmp_path / "res"), "--gt", str(gt_dir)]) == 0
    out = capsys.readouterr().out
    assert "CD2" in out and "mean" in out and "frame_002.obj" in out
    assert (tmp_path / "res" / "metrics.json").is_file()


def test_evaluate_missing_result_is_one_line(tmp_path, capsys):
    code = main(["evaluate", str(tmp_path / "nothing"), "--gt", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "nothing" in err


@pytest.mark.slow
def test_evaluate_r1_template_copies(phi_sft_dir, tmp_path, capsys):
    import shutil

    template = phi_sft_dir / "data" / "R1" / "0_R1_quad.obj"
    for i in range(2):
        p = mesh_path(tmp_path, i)
        p.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(template, p)
    assert main(["evaluate", str(tmp_path), "--gt", str(phi_sft_dir / "data" / "scenes" / "R1.json"),
                 "--allow-partial"]) == 0
    import json

    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["per_frame"]["cd2_1e-4m2"][0] < 1.0
