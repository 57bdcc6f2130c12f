"""How the shape phase's cost grows with the length of the video (issue 12).

    python benchmarks/bench_scaling.py [--lengths 50,100,200] [--out DIR] [--set key=value ...]

A synthetic hanging cloth blown by a gust (saft's own generator: a small template and small images, so
that the whole run fits in well under 40 minutes on a 2-core CPU) is made at each length and
reconstructed with the shape phases (`appearance.enabled=false`) under the given settings. Prints, per
length, the shape phase's seconds per frame and the mean CD2 against the known truth; the last line is
`shape_s_per_frame_ratio_200_vs_50=<ratio>` (first and last of --lengths).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from saft.evaluate import evaluate_result_dir, evaluate_static_template, ground_truth_spec_for
from saft.reconstruct import reconstruct
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.synthetic import HangingClothSpec, write_hanging_cloth

SMALL = dict(grid=8, size=0.4, image_size=64, focal=122.0, texture_size=64, gt_points=1500, gust=15.0)


def run(frames: int, out: Path, overrides: list[str]) -> dict:
    scene_dir = out / f"scene_{frames}"
    if not (scene_dir / "scene.json").is_file():
        write_hanging_cloth(scene_dir, HangingClothSpec(frames=frames, **SMALL))
    scene = load_scene(scene_dir)
    cfg = load_saft_config(None, ['run.device="cpu"', "appearance.enabled=false", "texture.epochs=40",
                                  "texture.size=64"] + overrides)
    result = out / f"result_{frames}"
    t0 = time.perf_counter()
    outcome = reconstruct(scene, cfg, result, quiet=True)
    wall = time.perf_counter() - t0
    spec = ground_truth_spec_for(scene)
    metrics = evaluate_result_dir(result, spec)
    static = evaluate_static_template(scene, spec)
    shape_s = outcome.timings.get("shape", wall)
    row = {"frames": frames, "shape_s": shape_s, "shape_s_per_frame": shape_s / frames,
           "cd2": metrics["mean"]["cd2_1e-4m2"], "cd2_last": metrics["per_frame"]["cd2_1e-4m2"][-1],
           "static_cd2": static["mean"]["cd2_1e-4m2"], "wall_s": wall}
    print(f"{frames:4d} frames  shape {shape_s:7.1f} s  {row['shape_s_per_frame']:.3f} s/frame  "
          f"CD2 {row['cd2']:.3f} (last frame {row['cd2_last']:.3f}, static template {row['static_cd2']:.3f})",
          flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--lengths", default="50,100,200")
    p.add_argument("--out", type=Path, default=Path("bench-scaling"))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    lengths = [int(n) for n in args.lengths.split(",")]
    rows = [run(n, args.out, args.set) for n in lengths]
    (args.out / "bench_scaling.json").write_text(json.dumps({"settings": args.set, "rows": rows}, indent=2))
    ratio = rows[-1]["shape_s_per_frame"] / rows[0]["shape_s_per_frame"]
    print(f"shape_s_per_frame_ratio_{lengths[-1]}_vs_{lengths[0]}={ratio:.3f}")


if __name__ == "__main__":
    main()
