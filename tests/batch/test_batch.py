"""`saft batch`: planning, the summary tables, and two tiny scenes (one grid setting) through a real local
Ray (2 CPUs, no dashboard) with a failing task, then resuming: finished tasks are skipped, one with a
checkpoint but no finish mark runs again with --resume."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from saft.batch.plan import parse_grid, plan_tasks, settings, task_state
from saft.batch.summary import TaskOutcome, summary_html
from saft.errors import SaftInputError
from saft.io_utils import write_image
from saft.scene import write_obj
from saft.synthetic.hanging_cloth import grid_template

REPO = Path(__file__).resolve().parents[2]
TINY = ['run.device="cpu"', "texture.epochs=2", "texture.size=16", "shape.initial_frames=2",
        "shape.add_frame_every=1", "shape.final_epochs=1", "appearance.enabled=false",
        "run.checkpoint_seconds=0"]


def _scene(folder: Path, shade: int) -> Path:
    """A 4×4 grid cloth, 3 frames of 40×32 px, with its own world-frame ground truth (the template)."""
    folder.mkdir(parents=True)
    mesh = grid_template(4, 0.4)
    verts = mesh.vertices + [0.0, 0.0, 1.0]   # 1 m in front of the camera
    write_obj(folder / "template.obj", mesh, verts)
    (folder / "camera.json").write_text(json.dumps({"width": 40, "height": 32,
                                                    "K": [[40, 0, 19.5], [0, 40, 15.5], [0, 0, 1]],
                                                    "world_to_camera": np.eye(4).tolist()}))
    for i in range(3):
        img = np.zeros((32, 40, 3), np.float32)
        img[8:24, 12:28] = (shade + 20 * i) / 255.0
        write_image(folder / "rgb" / f"{i:03d}.png", img)
        (folder / "gt").mkdir(exist_ok=True)
        np.save(folder / "gt" / f"{i:03d}.npy", verts + [0.0, 0.002 * i, 0.0])
    (folder / "scene.json").write_text(json.dumps({"fps": 25, "pinned_vertices": [12, 13, 14, 15],
                                                   "gravity": [0, 9.81, 0],
                                                   "ground_truth": {"dir": "gt", "frame": "world"}}))
    return folder


def test_grid_and_plan(tmp_path):
    grid = parse_grid(["shape.lambda_force=0,2e-4", "render.scale=0.5"])
    assert settings(grid) == [("shape.lambda_force=0,render.scale=0.5", ("shape.lambda_force=0", "render.scale=0.5")),
                              ("shape.lambda_force=2e-4,render.scale=0.5",
                               ("shape.lambda_force=2e-4", "render.scale=0.5"))]
    assert parse_grid(['x.y=[1, 2],[3, 4]'])[0][1] == ["[1, 2]", "[3, 4]"]
    for bad in (["novalues"], ["k="], ["k=1,,2"]):
        with pytest.raises(SaftInputError):
            parse_grid(bad)
    a = tmp_path / "a" / "R1.json"
    b = tmp_path / "b" / "R1.json"
    for p in (a, b):
        p.parent.mkdir()
        p.write_text("{}")
    tasks = plan_tasks([a], tmp_path / "out", ["x=1"], grid)
    assert [t.out_dir for t in tasks] == [(tmp_path / "out" / "R1" / s).resolve() for s, _ in settings(grid)]
    assert tasks[0].overrides == ("x=1", "shape.lambda_force=0", "render.scale=0.5")
    assert task_state(tasks[0]) == "new"
    with pytest.raises(SaftInputError, match="two scenes are named 'R1'"):
        plan_tasks([a, b], tmp_path / "out")
    with pytest.raises(SaftInputError, match="not found"):
        plan_tasks([tmp_path / "missing"], tmp_path / "out")


def test_summary_html_layout(tmp_path):
    """Scenes as columns, settings as rows, the mean last, the lowest of each column in bold."""
    outcomes = []
    for scene, vals in (("R1", (1.0, 2.0)), ("R2", (4.0, 2.5))):
        for setting, v in zip(("a=1", "a=2"), vals):
            t = plan_tasks([_dummy(tmp_path, scene)], tmp_path / "out", grid=[("a", ["1", "2"])])
            task = next(x for x in t if x.setting == setting)
            task.out_dir.mkdir(parents=True, exist_ok=True)
            (task.out_dir / "metrics.json").write_text(json.dumps({"mean": {"cd2_1e-4m2": v}}))
            outcomes.append(TaskOutcome(task, "done", 1.0))
    text = summary_html(outcomes)
    cd2 = text.split("<h2>CD2 (10⁻⁴ m²)</h2>")[1].split("</table>")[0]
    assert "<th>setting</th><th>R1</th><th>R2</th><th>mean</th>" in cd2
    assert "<tr><th>a=1</th><td><b>1.000</b></td><td>4.000</td><td>2.500</td></tr>" in cd2
    assert "<tr><th>a=2</th><td>2.000</td><td><b>2.500</b></td><td><b>2.250</b></td></tr>" in cd2


def _dummy(tmp_path: Path, name: str) -> Path:
    p = tmp_path / "scenes" / f"{name}.json"
    p.parent.mkdir(exist_ok=True)
    p.write_text("{}")
    return p


def _batch(args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO / "src"), "RAY_USAGE_STATS_ENABLED": "0"}
    # Generous: Ray's start-up and three tiny runs take about a minute on a quiet 2-core machine, several
    # times that when other jobs share the cores.
    return subprocess.run([sys.executable, "-m", "saft", "batch", *args], env=env, capture_output=True, text=True,
                          timeout=1200)


def _read_csv(path: Path) -> dict[tuple[str, str], dict]:
    with open(path, newline="") as fh:
        return {(r["scene"], r["setting"]): r for r in csv.DictReader(fh)}


@pytest.mark.slow
def test_batch_on_local_ray(tmp_path):
    pytest.importorskip("ray")
    a, b = _scene(tmp_path / "scenes" / "clothA", 120), _scene(tmp_path / "scenes" / "clothB", 160)
    bad = tmp_path / "scenes" / "broken"
    shutil.copytree(a, bad)
    (bad / "template.obj").write_text("v 0 0 0\nf 1 2 3 4\n")   # face indices past the vertices
    out = tmp_path / "batch"
    common = ["--out", str(out), "--gt", "--num-cpus", "2", "--quiet", *[x for item in TINY for x in ("--set", item)],
              "--grid", "shape.lambda_force=1e-4"]
    run = _batch([str(a), str(b), str(bad), *common])
    assert run.returncode == 1, run.stdout + run.stderr      # the broken scene fails, the others do not
    rows = _read_csv(out / "summary.csv")
    g = "shape.lambda_force=1e-4"
    assert set(rows) == {("clothA", g), ("clothB", g), ("broken", g)}
    for scene in ("clothA", "clothB"):
        r = rows[scene, g]
        assert r["status"] == "done", r
        assert float(r["wall_s"]) > 0 and float(r["cd2_1e-4m2"]) >= 0 and float(r["cd1_cm"]) > 0
        assert r["p2s_mm"] != "" and r["depth_cm"] != ""
        assert (out / scene / g / "meshes" / "frame_002.obj").is_file()
        assert "shape.lambda_force=1e-4" in json.loads((out / scene / g / "batch.json").read_text())["overrides"]
    assert rows["broken", g]["status"] == "failed" and "template.obj" in rows["broken", g]["error"]
    assert "failed" in run.stdout and "broken" in run.stdout
    html = (out / "summary.html").read_text()
    assert "<th>clothA</th><th>clothB</th><th>broken</th><th>mean</th>" in html
    assert '<td class="none">failed</td>' in html     # the failed scene's cell, and no mean over a missing one

    # resume: one task lost its finish mark (as if stopped after its checkpoint): only it runs, with --resume
    (out / "clothB" / g / "batch.json").unlink()
    again = _batch([str(a), str(b), *common])
    assert again.returncode == 0, again.stdout + again.stderr
    rows = _read_csv(out / "summary.csv")
    assert rows["clothA", g]["status"] == "skipped" and rows["clothB", g]["status"] == "done"
    log = (out / "logs" / f"clothB__{g}.log").read_text().splitlines()
    commands = [ln for ln in log if ln.startswith("$ ")]
    assert len(commands) == 2 and "--resume" not in commands[0] and commands[1].endswith("--resume")
    assert (out / "clothB" / g / "batch.json").is_file()
