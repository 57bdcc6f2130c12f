"""A small but real result folder in the documented layout (saft.result), built from a procedural motion.

8×8-vertex quad grid (0.4 m) hanging in front of the camera, a travelling sine wave through it, a
checker texture, log.csv for two phases, params.json, renders/, material maps, metrics.json, a depth pair.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from saft.io_utils import write_image
from saft.result import MESH_DIR, MESH_MTL, mesh_path, mtl_text
from saft.scene.camera import look_at
from saft.scene.mesh import QuadMesh, write_obj

N_FRAMES = 6
GRID = 8
FRAME_DT = 0.04


def grid_mesh(n: int = GRID, size: float = 0.4) -> QuadMesh:
    j, i = np.meshgrid(np.arange(n), np.arange(n))
    x = (j.ravel() / (n - 1) - 0.5) * size
    y = (i.ravel() / (n - 1) - 0.5) * size
    verts = np.stack([x, y, np.full_like(x, 1.0)], axis=1)
    uvs = np.stack([j.ravel() / (n - 1), 1.0 - i.ravel() / (n - 1)], axis=1)
    quads = []
    for r in range(n - 1):
        for c in range(n - 1):
            a = r * n + c
            quads.append([a, a + 1, a + n + 1, a + n])
    return QuadMesh(verts, np.asarray(quads), uvs)


def wave_frames(mesh: QuadMesh, n_frames: int = N_FRAMES) -> np.ndarray:
    out = []
    for f in range(n_frames):
        v = mesh.vertices.copy()
        phase = 2 * np.pi * (v[:, 0] / 0.4 - f / n_frames)
        v[:, 2] += 0.03 * np.sin(phase) * (v[:, 1] + 0.2) / 0.4  # pinned top row barely moves
        v[:, 1] += 0.002 * f
        out.append(v)
    return np.stack(out)


def _checker(h: int, w: int, cells: int = 4) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    c = ((yy * cells // h + xx * cells // w) % 2).astype(np.float32)
    img = np.stack([0.2 + 0.6 * c, 0.3 + 0.2 * c, 0.8 - 0.5 * c], axis=2)
    img[: h // 8, : w // 8] = [1.0, 0.1, 0.1]  # a red corner marks image row 0 (top-left) = v = 1
    return img


def build_result(folder: Path, *, with_material: bool = True, with_metrics: bool = True,
                 with_depth: bool = True, with_renders: bool = True) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    mesh = grid_mesh()
    frames = wave_frames(mesh)
    cam = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0],
                  np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]), 64, 48)
    (folder / "config.toml").write_text('[texture]\nepochs = 50\nlr = 0.01\n\n[shape]\nepochs = 30\n'
                                        'scene = "wave <test> & co"\n')
    (folder / "scene.json").write_text(json.dumps({"name": "wave", "source": "procedural", "frame_dt": FRAME_DT,
                                                   "camera": cam.to_json(), "gravity": [0.0, 9.81, 0.0]}))
    for f in range(len(frames)):
        write_obj(mesh_path(folder, f), mesh, frames[f], comment=f"frame {f}", mtllib=MESH_MTL)
    (folder / MESH_DIR / MESH_MTL).write_text(mtl_text())
    write_image(folder / "texture.png", _checker(32, 32))
    (folder / "params.json").write_text(json.dumps({
        "Y": 120.0, "B": 0.002, "S": 35.0, "log10_Y": float(np.log10(120.0)), "log10_B": float(np.log10(0.002)),
        "log10_S": float(np.log10(35.0)), "constant_acceleration": [0.0, 9.7, 0.1], "damping": 0.98,
        "frame_dt": FRAME_DT, "substeps": 20}))
    rng = np.random.default_rng(0)
    np.save(folder / "forces.npy", rng.normal(size=(len(frames) - 1, mesh.num_vertices, 3)) * 0.01)
    rows = []
    for phase, epochs in (("texture", 12), ("shape", 9)):
        for e in range(epochs):
            rows.append({"phase": phase, "epoch": e, "frames": min(len(frames), 2 + e),
                         "rgb": 0.5 * np.exp(-0.2 * e), "silhouette": 0.1 / (e + 1),
                         "regularizer": "" if phase == "texture" else 1e-3 * (1 + e), "seconds": 0.1 * e})
    with open(folder / "log.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (folder / "timings.json").write_text(json.dumps({"texture": 1.5, "shape": 12.25, "total": 13.75}))
    if with_renders:
        for f in range(len(frames)):
            target = _checker(40, 50) * (0.8 + 0.04 * f)
            rendered = np.clip(target + 0.05 * rng.normal(size=target.shape), 0, 1)
            write_image(folder / "renders" / f"frame_{f:03d}.png",
                        np.concatenate([rendered, target, np.abs(rendered - target)], axis=1))
    if with_material:
        write_image(folder / "material" / "diffuse.png", _checker(32, 32) * 0.9)
        write_image(folder / "material" / "roughness.png", np.full((32, 32), 0.7, np.float32))
        write_image(folder / "material" / "metallic.png", np.linspace(0, 1, 32 * 32, dtype=np.float32).reshape(32, 32))
        write_image(folder / "material" / "envmap.png", _checker(16, 32, 2))
        write_image(folder / "material" / "novel_view.png", _checker(40, 50, 5))
        for f in range(len(frames)):
            write_image(folder / "material" / "renders" / f"frame_{f:03d}.png", _checker(40, 100) * 0.9)
            write_image(folder / "material" / "novel_view" / f"frame_{f:03d}.png", _checker(40, 50) * 0.8)
    if with_metrics:  # the format saft.evaluate writes
        n = len(frames)
        (folder / "metrics.json").write_text(json.dumps({
            "num_frames": n, "seed": 0, "units": {"cd2_1e-4m2": "1e-4 m^2", "cd1_cm": "cm", "p2s_l1_mm": "mm"},
            "per_frame": {"cd2_1e-4m2": [1.0 + 0.1 * f for f in range(n)], "cd1_cm": [0.5 + 0.01 * f for f in range(n)],
                          "p2s_l1_mm": [2.0 - 0.1 * f for f in range(n)], "num_gt_points": [1000] * n},
            "mean": {"cd2_1e-4m2": 1.25, "cd1_cm": 0.525, "p2s_l1_mm": 1.75, "num_gt_points": 1000}}))
    if with_depth:
        (folder / "depth").mkdir()
        for f in (0, 3):
            gt = np.full((48, 64), np.nan, np.float32)
            gt[10:40, 12:52] = 1.0 + 0.01 * f
            rendered = np.nan_to_num(gt + 0.003 * rng.normal(size=gt.shape).astype(np.float32))  # 0 = empty
            np.savez(folder / "depth" / f"frame_{f:03d}.npz", rendered=rendered, target=gt)
    return folder


@pytest.fixture
def result_dir(tmp_path: Path) -> Path:
    return build_result(tmp_path / "result")


@pytest.fixture
def bare_result_dir(tmp_path: Path) -> Path:
    """Only what phase 1–2 write without ground truth: no material/, metrics.json, depth/."""
    return build_result(tmp_path / "bare", with_material=False, with_metrics=False, with_depth=False)


@pytest.fixture(scope="module")
def shared_result_dir(tmp_path_factory) -> Path:
    """A full result built once per test module (tests using it must not modify it)."""
    return build_result(tmp_path_factory.mktemp("shared") / "result")
