"""`saft evaluate` for phase 3: a result's material/ maps (and its phase-1 texture, the baseline) scored
against a scene's appearance ground truth (saft.evaluate.appearance), written into material/appearance.json."""

from __future__ import annotations

import json
from pathlib import Path

from saft.appearance.fit import load_appearance
from saft.evaluate.appearance import (HIGHER_IS_BETTER, METRIC_NAMES, appearance_metrics, beats, map_metrics,
                                      read_appearance_ground_truth, texture_baseline, true_geometry, uv_coverage)
from saft.io_utils import atomic_write_json, read_image
from saft.scene import load_scene

SUMMARY = Path("material") / "appearance.json"


def evaluate_appearance_result(result_dir, scene_dir, spp: int = 64, device="cpu", write: bool = True) -> dict | None:
    """{"phase3": metrics, "texture_only": metrics, "phase3_better": {metric: bool}} of a result folder,
    or None when the scene has no appearance ground truth or the result no material/ (phase 3 off).
    The relit novel views need the scene's true geometry (gt_vertices.npy, on gt_mesh.obj where the truth
    has its own mesh: saft.evaluate.appearance.true_geometry); without it only the map metrics are given. Adds the dict to material/appearance.json under "ground_truth_metrics"."""
    result_dir, scene_dir = Path(result_dir), Path(scene_dir)
    gt = read_appearance_ground_truth(scene_dir)
    if gt is None or not (result_dir / SUMMARY).is_file():
        return None
    scene = load_scene(scene_dir)
    est = load_appearance(result_dir)
    texture = read_image(result_dir / "texture.png")[..., :3]
    truth = true_geometry(scene_dir, scene.template)
    rows = {}
    for name, maps in (("phase3", (est.diffuse, est.roughness, est.metallic)), ("texture_only", texture_baseline(texture))):
        if truth is not None:
            rows[name] = appearance_metrics(*maps, gt, *truth, scene.camera, spp=spp, device=device)
        else:
            tri, uvs = scene.template.triangles, scene.template.uvs
            rows[name] = map_metrics(*maps, gt, uv_coverage(tri, uvs, gt.roughness.shape[0]))
    out = {**rows, "phase3_better": {k: bool(v) for k, v in beats(rows["phase3"], rows["texture_only"]).items()},
           "scene": str(scene_dir), "relit_spp": spp}
    if write:
        summary = json.loads((result_dir / SUMMARY).read_text())
        summary["ground_truth_metrics"] = out
        atomic_write_json(result_dir / SUMMARY, summary)
    return out


def format_appearance_table(metrics: dict) -> str:
    """Phase 3 and the texture-only baseline side by side, one metric a line, with the better one (or a tie)."""
    rows = [("appearance metric", "phase 3", "texture only", "better")]
    for k in METRIC_NAMES:
        if k in metrics["phase3"]:
            a, b = metrics["phase3"][k], metrics["texture_only"][k]
            better = "tie" if abs(a - b) < 1e-9 else ("phase 3" if metrics["phase3_better"][k] else "texture only")
            rows.append((f"{k} ({'higher' if HIGHER_IS_BETTER[k] else 'lower'} is better)", f"{a:.3f}", f"{b:.3f}", better))
    widths = [max(len(r[j]) for r in rows) for j in range(4)]
    return "\n".join(f"{r[0]:<{widths[0]}}  {r[1]:>{widths[1]}}  {r[2]:>{widths[2]}}  {r[3]}" for r in rows)
