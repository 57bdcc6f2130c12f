"""Accuracy and wall time of the default reconstruction on the real scene R1 (and its ablations).

    python benchmarks/bench_r1.py [--ablation full|no_re|no_rf|neither|no_sil|fixed_stiffness ...]
                                  [--out DIR] [--device cpu] [--frames N] [--repeats K] [--first-repeat K0] [--set key=value ...]

Runs `saft reconstruct ../shared/data/phi_sft/data/scenes/R1.json` (shape phases only: the appearance
phase is benchmarked by bench_appearance.py) and evaluates it against R1's ground truth. `--frames N`
reconstructs and scores only the first N frames (a quicker screen; the benchmark number is for all 50).

The result of one run moves with numerical noise, so settings are compared by the median and the spread
of `--repeats K` runs under perturbations that should not matter, in turn: (0) as given, (1) the
template moved by seeded Gaussian noise of 1e-9 m, (2) two torch threads instead of one, (3+) 1e-9 m
noise with other seeds. Prints one line per run, then per ablation the median, min and max of the mean
CD2 and, last, `r1_cd2_1e-4m2=<median mean CD2>` and `r1_wall_s=<median wall seconds>` of the first
ablation. Each run also prints where its time went: load, texture, shape (its epochs, and the rest: tracks,
set-up, the final rollout) and outputs.

`--profile` runs under torch.profiler (CPU, and CUDA when there is one) and writes OUT/.../profile.txt: per
saft.* range (saft.shape.simulate, .render, .regularizers, .backward, .step, .tracks) the host and device
time, then the ops with the most device and host time, and the kernel launches and host synchronisations.
The profiler records every op: use it with --frames 8 --set shape.final_epochs=8 or so.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import time
from contextlib import nullcontext
from pathlib import Path

import torch


from bench_physics_device import LAUNCH_EVENTS, SYNC_EVENTS
from saft.evaluate import evaluate_result_dir, ground_truth_spec_for
from saft.reconstruct import reconstruct
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene

ABLATIONS = {
    "full": [],
    "no_re": ["shape.lambda_energy=0"],
    "no_rf": ["shape.lambda_force=0"],
    "neither": ["shape.lambda_energy=0", "shape.lambda_force=0"],
    "no_sil": ["shape.lambda_sil=0"],
    "fixed_stiffness": ["shape.optimize_stiffness=false"],
    "no_track": ["shape.lambda_track=0"],
    "no_backtrack": ["shape.backtrack_ratio=0"],
    "no_final_decay": ["shape.final_lr_fraction=1"],
    "full_passes": ["shape.window=0"],
    # the paper's optimisation: no tracks, no backtracking, constant learning rates, every epoch from the template
    "paper_optim": ["shape.lambda_track=0", "shape.backtrack_ratio=0", "shape.final_lr_fraction=1", "shape.window=0",
                    "shape.final_epochs=24"],
}

R1 = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "phi_sft" / "data" / "scenes" / "R1.json"


def perturbation(k: int) -> tuple[list[str], int | None]:
    """Settings and template-noise seed of the k-th repeat (see the module docstring)."""
    if k == 0:
        return ["run.threads=1"], None
    if k == 2:
        return ["run.threads=2"], None
    return ["run.threads=1"], k


def _profiler(device: str):
    from torch.profiler import ProfilerActivity, profile
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() and device != "cpu" else [])
    return profile(activities=acts)


def _profile_table(prof) -> str:
    """The saft.* ranges, the top ops by device and by host time, launches and syncs (times in ms)."""
    ev = prof.key_averages()
    dev = lambda e: getattr(e, "device_time_total", getattr(e, "cuda_time_total", 0.0)) / 1e3  # noqa: E731
    selfdev = lambda e: getattr(e, "self_device_time_total", getattr(e, "self_cuda_time_total", 0.0)) / 1e3  # noqa: E731
    lines = [f"{'range':34s} {'calls':>7s} {'host ms':>10s} {'device ms':>10s}"]
    for e in sorted((e for e in ev if e.key.startswith("saft.")), key=lambda e: -e.cpu_time_total):
        lines.append(f"{e.key:34s} {e.count:7d} {e.cpu_time_total / 1e3:10.1f} {dev(e):10.1f}")
    for title, key in (("self device", selfdev), ("self host", lambda e: e.self_cpu_time_total / 1e3)):
        lines += ["", f"{'op (by ' + title + ' time)':60s} {'calls':>8s} {'ms':>10s}"]
        for e in sorted((e for e in ev if not e.key.startswith("saft.")), key=lambda e: -key(e))[:25]:
            lines.append(f"{e.key[:60]:60s} {e.count:8d} {key(e):10.1f}")
    launches = sum(e.count for e in ev if e.key in LAUNCH_EVENTS + ("cudaGraphLaunch",))
    syncs = sum(e.count for e in ev if e.key in SYNC_EVENTS)
    lines += ["", f"launches (kernels and graphs) {launches}, host synchronisations {syncs}"]
    return "\n".join(lines)


def run(ablation: str, out: Path, device: str, extra: list[str], frames: int | None = None, repeat: int = 0,
        profile: bool = False) -> dict:
    scene = load_scene(R1)
    if frames:
        scene = scene.with_frames(frames)
    settings, noise_seed = perturbation(repeat)
    if noise_seed is not None:
        scene = scene.with_template_noise(noise_seed)
    cfg = load_saft_config(None, [f'run.device="{device}"', "appearance.enabled=false"] + settings
                           + ABLATIONS[ablation] + extra)
    t0, c0 = time.perf_counter(), time.process_time()
    with _profiler(device) if profile else nullcontext() as prof:
        outcome = reconstruct(scene, cfg, out, resume=(out / "checkpoint" / "state.pt").is_file(), quiet=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if profile:
        table = _profile_table(prof)
        (out / "profile.txt").write_text(table + "\n")
        print(table, flush=True)
    epochs = {}
    with open(out / "log.csv") as f:
        for r in csv.DictReader(f):
            epochs[r["phase"]] = epochs.get(r["phase"], 0.0) + float(r["seconds"] or 0)
    metrics = evaluate_result_dir(out, ground_truth_spec_for(scene), allow_partial=bool(frames))
    mean = metrics["mean"]
    per_frame = metrics["per_frame"]["cd2_1e-4m2"]
    row = {"ablation": ablation, "repeat": repeat, "perturbation": settings + ([f"noise_seed={noise_seed}"] if noise_seed else []),
           "cd2_1e-4m2": mean["cd2_1e-4m2"], "cd2_last": per_frame[-1], "cd2_per_frame": per_frame,
           "cd1_cm": mean["cd1_cm"], "p2s_l1_mm": mean["p2s_l1_mm"], "depth_cm": mean.get("depth_cm"),
           "wall_s": wall, "cpu_s": cpu, "timings": outcome.timings, "epoch_seconds": epochs}
    (out / "bench_r1.json").write_text(json.dumps(row, indent=2))
    print(f"{ablation:16s} run {repeat}  CD2 {mean['cd2_1e-4m2']:.3f} (last frame {per_frame[-1]:.3f})  "
          f"CD1 {mean['cd1_cm']:.3f} cm  p2s {mean['p2s_l1_mm']:.2f} mm  δ {mean.get('depth_cm', float('nan')):.3f} cm  "
          f"wall {wall / 60:.1f} min  CPU {cpu / 60:.1f} min", flush=True)
    t = outcome.timings
    print(f"  time (s): set-up {t.get('setup', 0):.1f}, frames {t.get('load_frames', 0):.1f}, estimate "
          f"{t.get('estimate', 0):.1f}, texture {t.get('texture', 0):.1f} (epochs "
          f"{epochs.get('texture', 0):.1f}), shape {t.get('shape', 0):.1f} (epochs {epochs.get('shape', 0):.1f}, "
          f"the rest {t.get('shape', 0) - epochs.get('shape', 0):.1f}), outputs {t.get('outputs', 0):.1f}", flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ablation", nargs="+", default=["full"], choices=sorted(ABLATIONS))
    p.add_argument("--out", type=Path, default=Path("bench-r1"))
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames (quick experiments)")
    p.add_argument("--repeats", type=int, default=1, help="runs per ablation under perturbations that should not matter")
    p.add_argument("--first-repeat", type=int, default=0,
                   help="start at this perturbation (to run the repeats of one setting as parallel processes)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--profile", action="store_true", help="torch.profiler over each run (see above)")
    args = p.parse_args()
    if not R1.is_file():
        raise SystemExit(f"R1 not found at {R1} (the shared/ folder beside the repository)")
    medians, walls = [], []
    for a in args.ablation:
        rows = [run(a, args.out / a / f"run{k}", args.device, args.set, args.frames, k, args.profile) for k in range(args.first_repeat, args.first_repeat + args.repeats)]
        cd2 = [r["cd2_1e-4m2"] for r in rows]
        medians.append(statistics.median(cd2))
        walls += [r["wall_s"] for r in rows] if a == args.ablation[0] else []
        print(f"{a:16s} median CD2 {medians[-1]:.3f}  min {min(cd2):.3f}  max {max(cd2):.3f}  "
              f"max/min {max(cd2) / min(cd2):.2f}  median last frame {statistics.median(r['cd2_last'] for r in rows):.3f}",
              flush=True)
    print(f"r1_cd2_1e-4m2={medians[0]:.4f}")
    print(f"r1_wall_s={statistics.median(walls):.1f}")


if __name__ == "__main__":
    main()
