"""Accuracy and wall time of the default shape reconstruction on the benchmark scenes with ground truth.

    python benchmarks/bench_scenes.py [--scenes-dir DIR] [--only a_pinned,b_unpinned,...] [--out DIR]
                                      [--device cpu] [--set key=value ...]
                                      [--grid N] [--frames N] [--image-size PX] [--spp N] [--noise-seed K]

The scenes (saft.synthetic.benchmark_scenes: a cloth hanging in wind, a cloth held at two corners swinging, a corner
grabbed and folded towards the camera; each with and without pinned vertices) are generated into
--scenes-dir (default /tmp/saft-bench-scenes) when missing or made with other sizes. Each is reconstructed
by `saft.reconstruct.reconstruct` with the default config (shape phases only: `appearance.enabled=false`;
--set passes overrides) and scored against its ground truth. Prints per scene: static-template CD2 mean,
saft CD2 mean and last frame (1e-4 m²), wall and CPU time of the reconstruction; writes OUT/bench_scenes.json; the last line is
`scenes_cd2_median=<median over the scenes of the mean CD2>`. --noise-seed K > 0 moves the template by
seeded Gaussian noise of 1e-9 m before the reconstruction (a perturbation that should not matter, as in
bench_r1.py; the scoring uses the scene as given): the runs are deterministic, so repeats need it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import asdict, replace
from pathlib import Path

from saft.evaluate import evaluate_result_dir, evaluate_static_template, ground_truth_spec_for
from saft.io_utils import atomic_write_json
from saft.reconstruct import reconstruct
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.synthetic.benchmark_scenes import SCENARIOS, BenchSceneSpec, scene_names, write_benchmark_scenes


def run_scene(folder: Path, out: Path, device: str, extra: list[str], noise_seed: int = 0) -> dict:
    scene = load_scene(folder)
    cfg = load_saft_config(None, [f'run.device="{device}"', "appearance.enabled=false"] + extra)
    gt = ground_truth_spec_for(scene)
    static = evaluate_static_template(scene, gt)
    if noise_seed > 0:
        scene = scene.with_template_noise(noise_seed)
    t0, c0 = time.perf_counter(), time.process_time()
    reconstruct(scene, cfg, out, resume=(out / "checkpoint" / "state.pt").is_file(), quiet=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    metrics = evaluate_result_dir(out, gt)
    per_frame = metrics["per_frame"]["cd2_1e-4m2"]
    row = {"scene": folder.name, "static_cd2_mean": static["mean"]["cd2_1e-4m2"],
           "static_cd2_last": static["per_frame"]["cd2_1e-4m2"][-1], "cd2_mean": metrics["mean"]["cd2_1e-4m2"],
           "cd2_last": per_frame[-1], "cd2_per_frame": per_frame, "cd1_cm": metrics["mean"]["cd1_cm"],
           "p2s_l1_mm": metrics["mean"]["p2s_l1_mm"], "wall_s": wall, "cpu_s": cpu}
    print(f"{folder.name:12s} static CD2 {row['static_cd2_mean']:8.3f}  saft CD2 mean {row['cd2_mean']:8.3f}  "
          f"last {row['cd2_last']:8.3f}  wall {wall / 60:5.1f} min  CPU {cpu / 60:5.1f} min", flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes-dir", type=Path, default=Path("/tmp/saft-bench-scenes"))
    p.add_argument("--only", default="", help="comma-separated scene names (default: all: "
                                             + ",".join(scene_names()) + ")")
    p.add_argument("--out", type=Path, default=Path("bench-scenes"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    d = BenchSceneSpec()
    p.add_argument("--grid", type=int, default=d.grid, help="template vertices per side")
    p.add_argument("--frames", type=int, default=d.frames)
    p.add_argument("--image-size", type=int, default=d.image_size)
    p.add_argument("--spp", type=int, default=d.spp)
    p.add_argument("--noise-seed", type=int, default=0, help="move the template by 1e-9 m noise of this seed (0 = no)")
    args = p.parse_args()
    names = [n for n in args.only.split(",") if n] or scene_names()
    unknown = sorted(set(names) - set(scene_names()))
    if unknown:
        raise SystemExit(f"--only: unknown scene(s) {', '.join(unknown)} (known: {', '.join(scene_names())})")
    spec = replace(d, grid=args.grid, frames=args.frames, image_size=args.image_size, spp=args.spp)
    t0 = time.perf_counter()
    write_benchmark_scenes(args.scenes_dir, spec, [s for s in SCENARIOS if any(n[0] == s for n in names)])
    print(f"scenes ready in {args.scenes_dir} ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = []
    for name in names:
        rows.append(run_scene(args.scenes_dir / name, args.out / name, args.device, args.set, args.noise_seed))
        atomic_write_json(args.out / "bench_scenes.json",
                          {"spec": asdict(spec), "overrides": args.set, "noise_seed": args.noise_seed,
                           "scenes": rows})
    print(f"scenes_cd2_median={statistics.median(r['cd2_mean'] for r in rows):.4f}")


if __name__ == "__main__":
    main()
