"""Accuracy and wall time of the default reconstruction on the real scene R1 (and its ablations).

    python benchmarks/bench_r1.py [--ablation full|no_re|no_rf|neither|no_sil|fixed_stiffness ...]
                                  [--out DIR] [--device cpu] [--frames N] [--set key=value ...]

Runs `saft reconstruct ../shared/data/phi_sft/data/scenes/R1.json` (shape phases only: the appearance
phase is benchmarked by bench_appearance.py) and evaluates it against R1's ground truth. Prints one line
per ablation and, last, `r1_cd2_1e-4m2=<mean CD2>` for the first one. `--frames N` reconstructs and scores
only the first N frames (a quick experiment; the benchmark number is for all 50).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

ABLATIONS = {
    "full": [],
    "no_re": ["shape.lambda_energy=0"],
    "no_rf": ["shape.lambda_force=0"],
    "neither": ["shape.lambda_energy=0", "shape.lambda_force=0"],
    "no_sil": ["shape.lambda_sil=0"],
    "fixed_stiffness": ["shape.optimize_stiffness=false"],
}

R1 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "phi_sft" / "data" / "scenes" / "R1.json"


def run(ablation: str, out: Path, device: str, extra: list[str], frames: int | None = None) -> dict:
    from saft.evaluate import evaluate_result_dir, ground_truth_spec_for
    from saft.reconstruct import reconstruct
    from saft.reconstruct.config import load_saft_config
    from saft.scene import load_scene

    scene = load_scene(R1)
    if frames:
        scene = scene.with_frames(frames)
    cfg = load_saft_config(None, [f'run.device="{device}"', "appearance.enabled=false"] + ABLATIONS[ablation]
                           + extra)
    t0 = time.perf_counter()
    outcome = reconstruct(scene, cfg, out, resume=(out / "checkpoint" / "state.pt").is_file(), quiet=True)
    wall = time.perf_counter() - t0
    metrics = evaluate_result_dir(out, ground_truth_spec_for(scene), allow_partial=bool(frames))
    mean = metrics["mean"]
    row = {"ablation": ablation, "cd2_1e-4m2": mean["cd2_1e-4m2"], "cd1_cm": mean["cd1_cm"],
           "p2s_l1_mm": mean["p2s_l1_mm"], "depth_cm": mean.get("depth_cm"), "wall_s": wall, "timings": outcome.timings}
    (out / "bench_r1.json").write_text(json.dumps(row, indent=2))
    print(f"{ablation:16s} CD2 {mean['cd2_1e-4m2']:.3f}  CD1 {mean['cd1_cm']:.3f} cm  "
          f"p2s {mean['p2s_l1_mm']:.2f} mm  δ {mean.get('depth_cm', float('nan')):.3f} cm  wall {wall / 60:.1f} min",
          flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ablation", nargs="+", default=["full"], choices=sorted(ABLATIONS))
    p.add_argument("--out", type=Path, default=Path("bench-r1"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames (quick experiments)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    if not R1.is_file():
        raise SystemExit(f"R1 not found at {R1} (the shared/ folder beside the repository)")
    rows = [run(a, args.out / a, args.device, args.set, args.frames) for a in args.ablation]
    print(f"r1_cd2_1e-4m2={rows[0]['cd2_1e-4m2']:.4f}")


if __name__ == "__main__":
    main()
