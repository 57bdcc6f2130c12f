"""Why saft loses clips that start mid-motion, curved (issue 29; `bench_appearance --start 24`'s scenes).

Three checks, each printing its numbers (BENCHMARKS.md, "A flat rest shape for clips that start curved"):

* ``forward``: no optimisation. The appearance scenes' true motion (benchmark_scenes scenario "a", saft's
  simulator, flat at rest, wind along +z towards the camera) continued from frame START with the true wind,
  once with the template (frame START) as the rest shape and once flattened (physics.rest_shape), with the
  true velocity or none, with the true or saft's default physical parameters, or with no wind. Prints the
  mean vertex distance to the truth (cm) and the cloth's mean z (towards the camera) at the last frame.
* ``shape SCENE OUT [key=value ...] [--noise-seed K]``: saft's texture + shape phases on a scene (phase 3 off,
  as bench_appearance's own motion, one torch thread) with config overrides; prints the mean and per-frame
  CD2. --noise-seed K > 0 moves the template by 1e-9 m noise of seed K (a repeat of the deterministic run).
* ``tracks SCENE ...``: the shape phase's point tracks (default settings), started at the true projections
  of every vertex, against the true projections per frame (pixels; no visibility test).

    PYTHONPATH=src nice -n 10 python3 benchmarks/diagnose_curved_start.py forward [--start 24]
    PYTHONPATH=src nice -n 10 python3 benchmarks/diagnose_curved_start.py shape SCENE OUT 'physics.rest_shape="flat"'
    PYTHONPATH=src nice -n 10 python3 benchmarks/diagnose_curved_start.py tracks SCENE [SCENE ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from saft.evaluate import GroundTruthSpec, evaluate_result_dir
from saft.physics import ClothTopology, PhysicsParams, rollout
from saft.physics.simulation import GRAVITY
from saft.reconstruct import reconstruct
from saft.reconstruct.config import SaftConfig, load_saft_config
from saft.reconstruct.tracks import end_at_appearance_jumps, project, track_points
from saft.scene import load_scene
from saft.synthetic.benchmark_scenes import BenchSceneSpec, grid_template, wind_field


def forward(start: int, frames: int) -> None:
    spec = BenchSceneSpec(grid=17, size=0.4, frames=start + frames, frame_dt=0.02, seed=0)  # the appearance scenes'
    n, F, dt, S = spec.grid, spec.frames, spec.frame_dt, spec.substeps
    tpl = grid_template(n, spec.size)
    pins = torch.arange(n)
    wind = wind_field(tpl.vertices, F, dt, spec.wind, spec.seed)
    f64 = dict(dtype=torch.float64)

    def params(log10_Y, log10_B, log10_S, damping, accel):
        return PhysicsParams(*(torch.tensor(v, **f64) for v in (log10_Y, log10_B, log10_S, damping)),
                             torch.tensor(GRAVITY, **f64), torch.tensor(accel, **f64))

    true = (spec.log10_Y, spec.log10_B, spec.log10_S, spec.damping)
    topo = ClothTopology.from_quads(tpl.vertices, tpl.quads, **f64)
    with torch.no_grad():  # every substep a frame of its own: the velocity at frame `start` is exact
        sub = rollout(topo, topo.template, None, params(*true, np.repeat(wind[:start], S, axis=0)),
                      num_frames=start * S + 1, substeps=1, frame_dt=dt / S, pinned=pins)
        truth = rollout(topo, topo.template, None, params(*true, wind), num_frames=F, substeps=S, frame_dt=dt,
                        pinned=pins)[start:].numpy()
    x0, v0 = sub[-1], (sub[-1] - sub[-2]) / (dt / S)
    print(f"frame {start}: mean speed {float(v0.norm(dim=1).mean()):.3f} m/s; true mean z per 4 frames "
          f"{np.round(truth[::4, :, 2].mean(1), 3).tolist()}")
    saft_defaults = (np.log10(200.0), -3.0, -4.0, 0.9)
    cases = [(rest, vname, v, pname, p, wname, w)
             for rest in ("template", "flat")
             for vname, v, pname, p, wname, w in (("true", v0, "true", true, "true", wind[start:]),
                                                  ("0", None, "true", true, "true", wind[start:]),
                                                  ("0", None, "saft defaults", saft_defaults, "true", wind[start:]),
                                                  ("0", None, "true", true, "none", 0 * wind[start:]))]
    print("| rest shape | v0 | physical parameters | wind | error cm, frames 4 / 8 / 16 / last | mean | z last (true "
          f"{truth[-1, :, 2].mean():.3f}) |\n|---|---|---|---|---|---|---|")
    for rest, vname, v, pname, p, wname, w in cases:
        t = ClothTopology.from_quads(x0.numpy(), tpl.quads, rest_shape=rest, **f64)
        with torch.no_grad():
            x = rollout(t, x0, v, params(*p, w), num_frames=frames, substeps=S, frame_dt=dt, pinned=pins).numpy()
        err = np.linalg.norm(x - truth, axis=2).mean(1) * 100
        print(f"| {rest} | {vname} | {pname} | {wname} | {err[4]:.2f} / {err[8]:.2f} / {err[16]:.2f} / {err[-1]:.2f} "
              f"| {err.mean():.2f} | {x[-1, :, 2].mean():.3f} |")


def shape(scene_dir: Path, out: Path, sets: list[str], noise_seed: int = 0) -> None:
    t = time.time()
    if not (out / "timings.json").is_file():
        cfg = load_saft_config(None, ['run.device="cpu"', "run.threads=1", "appearance.enabled=false", *sets])
        scene = load_scene(scene_dir)
        reconstruct(scene.with_template_noise(noise_seed) if noise_seed else scene, cfg, out, overwrite=True,
                    quiet=True)
    m = evaluate_result_dir(out, GroundTruthSpec(scene_dir / "gt"), write=True)
    print(json.dumps({"scene": str(scene_dir), "sets": sets, "noise_seed": noise_seed,
                      "mean_cd2": m["mean"]["cd2_1e-4m2"],
                      "per_frame": [round(x, 3) for x in m["per_frame"]["cd2_1e-4m2"]],
                      "seconds": round(time.time() - t, 1)}))


def tracks(scene_dirs: list[str]) -> None:
    c = SaftConfig().shape
    for d in scene_dirs:
        s = load_scene(d)
        rgb, mask = s.frames.load()
        uv = project(torch.as_tensor(np.load(Path(d) / "gt_vertices.npy")), s.camera)[0].numpy()
        pts, valid = track_points(rgb, mask, uv[0], np.ones(uv.shape[1], bool), c.track_fb_threshold,
                                  c.track_reanchor_radius)
        valid = end_at_appearance_jumps(rgb, pts, valid, c.track_jump_ratio, c.track_jump_floor)
        err = np.linalg.norm(pts - uv, axis=2)
        print(Path(d).name)
        for k in sorted({1, 4, 8, 12, 16, 20, 24, len(uv) - 1}):
            e = err[k][valid[k]]
            step = np.median(np.linalg.norm(uv[k] - uv[k - 1], axis=1))
            if e.size == 0:
                print(f"  frame {k:2d}: no track left (true step {step:.2f} px)")
                continue
            print(f"  frame {k:2d}: {valid[k].mean():.2f} of the vertices tracked, error median {np.median(e):.2f} px,"
                  f" 90 % {np.percentile(e, 90):.2f} px, {np.mean(e > 3):.2f} beyond 3 px (true step {step:.2f} px)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="check", required=True)
    f = sub.add_parser("forward")
    f.add_argument("--start", type=int, default=24)
    f.add_argument("--frames", type=int, default=32)
    s = sub.add_parser("shape")
    s.add_argument("scene", type=Path)
    s.add_argument("out", type=Path)
    s.add_argument("sets", nargs="*")
    s.add_argument("--noise-seed", type=int, default=0)
    t = sub.add_parser("tracks")
    t.add_argument("scenes", nargs="+")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.check == "forward":
        forward(a.start, a.frames)
    elif a.check == "shape":
        shape(a.scene, a.out, a.sets, a.noise_seed)
    else:
        tracks(a.scenes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
