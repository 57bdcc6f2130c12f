"""The demo's synthetic hanging cloth (16×16 template, 20 frames, 200×200 px, rendered by saft's own
rasterizer), reconstructed with the shape phases; with or without its pinned top row.

    python benchmarks/bench_hanging.py NAME [--free] [--frames N] [--out DIR] [--set key=value ...]

`--free` hands saft the same video with no pinned vertices (the paper's setting: the learned forces must
hold the cloth up). Prints one JSON line: mean and last-frame CD2 (1e-4 m²), the static template's mean
CD2, and the wall time.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from saft.evaluate import evaluate_result_dir, evaluate_static_template, ground_truth_spec_for
from saft.reconstruct import reconstruct
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.synthetic import HangingClothSpec, write_hanging_cloth


def scene_folder(root: Path, frames: int, free: bool) -> Path:
    base = root / f"scene_{frames}"
    if not (base / "scene.json").is_file():
        write_hanging_cloth(base, HangingClothSpec(frames=frames))
    if not free:
        return base
    folder = root / f"scene_{frames}_free"
    if not (folder / "scene.json").is_file():
        shutil.copytree(base, folder, dirs_exist_ok=True)
        meta = json.loads((folder / "scene.json").read_text())
        meta.pop("pinned_vertices", None)
        (folder / "scene.json").write_text(json.dumps(meta))
    return folder


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name")
    p.add_argument("--free", action="store_true", help="no pinned vertices in the scene handed to saft")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--out", type=Path, default=Path("bench-hanging"))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = p.parse_args()
    scene = load_scene(scene_folder(a.out, a.frames, a.free))
    out = a.out / "results" / a.name
    shutil.rmtree(out, ignore_errors=True)
    cfg = load_saft_config(None, ["texture.epochs=100", "texture.size=256", 'run.device="cpu"', "run.threads=1",
                                  "appearance.enabled=false"] + a.set)
    t0 = time.perf_counter()
    reconstruct(scene, cfg, out, quiet=True)
    wall = time.perf_counter() - t0
    spec = ground_truth_spec_for(scene)
    m = evaluate_result_dir(out, spec)
    static = evaluate_static_template(scene, spec)["mean"]["cd2_1e-4m2"]
    print(json.dumps({"name": a.name, "free": a.free, "set": a.set, "cd2": m["mean"]["cd2_1e-4m2"],
                      "cd2_last": m["per_frame"]["cd2_1e-4m2"][-1], "static": static, "wall_s": wall}), flush=True)


if __name__ == "__main__":
    main()
