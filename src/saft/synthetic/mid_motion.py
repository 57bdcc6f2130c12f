"""Scenes that start mid-motion: a written benchmark scene with its first frames dropped.

Real videos often start while the cloth is already moving; every generated scene starts it at rest. Dropping
the first `start` frames of a scene gives one whose frame 0 has the velocity the simulator had reached
there. The template becomes the ground-truth shape of the new frame 0 (saft takes the template as frame 0's
geometry and its rest shape): resampled from the ground-truth mesh onto the template's grid when the two
differ (the independent scenes' 40 × 40 Newton mesh against the 25 × 25 template, matching material
coordinates row-major), taken as it is when they are the same mesh (the model-matched twins). Frames,
masks, ground-truth points and vertices, camera, pins and gravity are the source's, renumbered from 0.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from saft.scene import load_scene
from saft.scene.native import read_json
from saft.synthetic.benchmark_scenes import DONE_FILE, write_scene_folder
from saft.synthetic.independent_scenes import resample_grid


def template_at(gt_vertices: np.ndarray, grid: int) -> np.ndarray:
    """(grid², 3) template positions from one frame's ground-truth vertices (n², 3) of a square grid mesh."""
    n = int(round(np.sqrt(len(gt_vertices))))
    if n * n != len(gt_vertices):
        raise ValueError(f"ground truth of {len(gt_vertices)} vertices is not a square grid")
    if n == grid:
        return np.asarray(gt_vertices, dtype=np.float64)
    return resample_grid(np.asarray(gt_vertices, dtype=np.float64).reshape(n, n, 3), grid)


def write_mid_motion_scene(source: str | Path, dest: str | Path, start: int) -> Path:
    """Write `source` (a generated scene folder with gt/ and gt_vertices.npy) without its first `start`
    frames to `dest`; skipped when `dest` was already made from the same source and start."""
    source, dest = Path(source), Path(dest)
    info = {**read_json(source / DONE_FILE), "mid_motion": {"source": source.name, "start": int(start)}}
    try:
        if json.loads((dest / DONE_FILE).read_text()) == json.loads(json.dumps(info)):
            return dest
    except (OSError, ValueError):
        pass
    scene = load_scene(source)
    n = len(scene.frames)
    if not 0 < start < n - 1:
        raise ValueError(f"start must be in 1..{n - 2} for a scene of {n} frames, got {start}")
    positions = np.load(source / "gt_vertices.npy")
    grid = int(round(np.sqrt(len(scene.template.vertices))))
    template = replace(scene.template, vertices=template_at(positions[start], grid))
    rgb, mask = scene.frames.load(range(start, n))
    gt_points = [np.load(source / "gt" / f"frame_{i:03d}.npy") for i in range(start, n)]
    mid = replace(scene, name=dest.name, template=template)
    write_scene_folder(dest, mid, rgb, mask, gt_points, positions[start:], info)
    return dest


__all__ = ["template_at", "write_mid_motion_scene"]
