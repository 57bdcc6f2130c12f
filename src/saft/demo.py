"""`saft demo`: make a synthetic hanging-cloth scene, reconstruct it, and compare with the static template."""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path
from saft.evaluate import evaluate_result_dir, evaluate_static_template, format_comparison_table, ground_truth_spec_for
from saft.reconstruct import reconstruct
from saft.reconstruct.checkpoint import checkpoint_path
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.synthetic.hanging_cloth import HangingClothSpec, write_hanging_cloth


log = logging.getLogger("saft")

# The demo runs the published method's defaults; only what a 20-frame, 200×200 scene needs less of is lowered.
DEMO_NAME = "synthetic hanging cloth (saft demo)"
DEMO_OVERRIDES = ["texture.epochs=100", "texture.size=256"]


def run_demo(out: str | Path, quiet: bool = False, device: str = "auto", overrides: list[str] | None = None,
             spec=None) -> dict:
    out = Path(out)
    t0 = time.perf_counter()
    scene_dir = out / "scene"
    if not (scene_dir / "scene.json").is_file():
        log.info("making the synthetic scene in %s", scene_dir)
        write_hanging_cloth(scene_dir, spec or HangingClothSpec())
    scene = replace(load_scene(scene_dir), name=DEMO_NAME)
    cfg = load_saft_config(None, DEMO_OVERRIDES + [f'run.device="{device}"'] + list(overrides or []))
    result_dir = out / "result"   # beside the scene, never around it (saft.reconstruct.out_dir)
    reconstruct(scene, cfg, result_dir, resume=checkpoint_path(result_dir).is_file(), quiet=quiet)
    spec_gt = ground_truth_spec_for(scene, None)
    ours = evaluate_result_dir(result_dir, spec_gt)
    static = evaluate_static_template(scene, spec_gt)
    print(format_comparison_table({"saft": ours, "static template": static}))
    log.info("demo finished in %.0f s; results in %s", time.perf_counter() - t0, result_dir)
    return {"ours": ours, "static": static}
