"""Appearance benchmark with ground truth (issue 28): phase 3 against the true maps and lights, per fabric.

For each fabric kind (saft.synthetic.fabrics: cotton, print, plaid, satin, lame) a cloth in wind (saft's
simulator, or with ``--motion newton`` NVIDIA Newton's on a finer mesh) is path-traced by Mitsuba with the
fabric's known base colour / roughness / metallic maps under the "video" environment map
(saft.synthetic.appearance.write_appearance_scene; scenes are cached under --root). Rows per scene (metrics:
saft.evaluate.appearance):

* ``texture only``: the phase-1 texture (saft reconstruct, texture phase) as the diffuse map, roughness 1,
  metallic 0 — no phase 3 at all;
* ``phase 3, true motion``: fit_appearance on the ground-truth vertices (the paper's protocol), started
  from that phase-1 texture (Newton's truth resampled to the template: true_motion_on_template);
* ``phase 3, saft motion`` (``--own-motion``): phase 3 on saft's own motion, as in ``saft reconstruct``:
  the run's texture and shape phases (``saft reconstruct`` with phase 3 off, cached under --root, since they
  do not depend on the appearance settings), then fit_appearance on its meshes and its phase-1 texture,
  scored the same way (the relit views use the true geometry, Newton's own fine mesh where it has one:
  saft.evaluate.appearance.true_geometry, so only the maps are judged).

    PYTHONPATH=src nice -n 10 python3 benchmarks/bench_appearance.py                 # 16 frames, 160x120
    PYTHONPATH=src nice -n 10 python3 benchmarks/bench_appearance.py --frames 32 --width 320 --height 240
    PYTHONPATH=src python3 benchmarks/bench_appearance.py --fabrics lame --set lambda_metallic_l1=0   # ablation
    PYTHONPATH=src python3 benchmarks/bench_appearance.py --start 24 ...   # frame 0 billowed, not flat

``--start N`` drops the first N simulated frames, so that frame 0 (and the template) is the cloth already
curved by the wind and its shading varies across it (AppearanceSceneSpec.start); scenes and runs are cached
under names ending in ``_sN``. ``--motion newton``: the motion of independent_scenes' "gust" scenario from
Newton's VBD on a 40 × 40 mesh (the template 17 × 17, 30 fps; AppearanceSceneSpec.motion), not saft's own
simulator on the template's mesh, with Newton's self-contact (AppearanceSceneSpec.self_contact; the clips made
before it, whose truth crossed itself, are made again, and the cached runs of a scene made again are redone):
cached under names with ``_newton`` in them.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from saft.appearance import fit_appearance
from saft.appearance.config import AppearanceConfig, cpu_profile, cuda_profile, paper_profile
from saft.config_io import merge_overrides
from saft.evaluate import GroundTruthSpec, evaluate_result_dir
from saft.evaluate.appearance import (METRIC_NAMES, appearance_metrics, read_appearance_ground_truth, texture_baseline,
                                      true_geometry)
from saft.io_utils import read_image
from saft.reconstruct import reconstruct
from saft.reconstruct.config import load_saft_config
from saft.scene import load_scene
from saft.scene.mesh import read_obj
from saft.synthetic.appearance import (AppearanceSceneSpec, mark_run, run_is_current, true_motion_on_template,
                                      write_appearance_scene)
from saft.synthetic.fabrics import FABRICS


def phase1_texture(scene_dir: Path, out: Path, threads: int = 0) -> np.ndarray:
    """The texture of saft's phase 1 on this scene (cached in `out`, made again when the scene was)."""
    if run_is_current(out, scene_dir, "texture.png"):
        return read_image(out / "texture.png")[..., :3]
    cfg = load_saft_config(None, ['run.device="cpu"', f"run.threads={threads}", "shape.enabled=false",
                                  "appearance.enabled=false"])
    texture = reconstruct(load_scene(scene_dir), cfg, out, overwrite=True, quiet=True).texture
    mark_run(out, scene_dir)
    return texture


def own_motion(scene_dir: Path, out: Path, threads: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """saft's own motion (F, V, 3), its phase-1 texture and the motion's mean CD2 (1e-4 m²): `saft
    reconstruct` of the scene with phase 3 off (cached in `out`: timings.json is written last; made again when
    the scene was)."""
    if not run_is_current(out, scene_dir, "timings.json"):
        cfg = load_saft_config(None, ['run.device="cpu"', f"run.threads={threads}", "appearance.enabled=false"])
        reconstruct(load_scene(scene_dir), cfg, out, overwrite=True, quiet=True)
        mark_run(out, scene_dir)
    files = sorted((out / "meshes").glob("frame_*.obj"))
    positions = np.stack([read_obj(p).vertices for p in files]).astype(np.float64)
    cd2 = evaluate_result_dir(out, GroundTruthSpec(scene_dir / "gt"), write=False)["mean"]["cd2_1e-4m2"]
    return positions, read_image(out / "texture.png")[..., :3], float(cd2)


def row(label: str, maps, gt, scene, truth, spp: int, seconds=(0.0, 0.0), device="cpu") -> dict:
    """One row's metrics; truth = (vertices, triangles, uvs) of the true geometry (true_geometry); the relit
    views rendered by Mitsuba on `device`."""
    m = appearance_metrics(*maps, gt, *truth, scene.camera, spp=spp, device=device)
    return {"method": label, **{k: m[k] for k in METRIC_NAMES}, "fit_wall_s": seconds[0], "fit_cpu_s": seconds[1]}


def save_comparison(path: Path, res, gt, texture) -> None:
    """One image: rows (diffuse, roughness, metallic) × columns (phase-1 texture, estimate, truth), and the
    estimated env map beside the true one."""
    import torch
    import torch.nn.functional as F

    from saft.appearance.params import linear_to_srgb
    from saft.io_utils import write_image

    def fit(a, s=256):
        t = torch.as_tensor(np.asarray(a, np.float32).reshape(*np.shape(a)[:2], -1)).permute(2, 0, 1)[None]
        t = F.interpolate(t, size=(s, s), mode="area" if t.shape[-1] > s else "bilinear")[0].permute(1, 2, 0)
        return t.expand(-1, -1, 3).numpy()

    srgb = lambda x: linear_to_srgb(torch.as_tensor(np.asarray(x, np.float32))).numpy()
    rows = [np.concatenate([fit(texture), fit(srgb(res.diffuse)), fit(srgb(gt.base_color))], 1),
            np.concatenate([np.zeros((256, 256, 3)), fit(res.roughness), fit(gt.roughness)], 1),
            np.concatenate([np.zeros((256, 256, 3)), fit(res.metallic), fit(gt.metallic)], 1)]
    env = lambda e: srgb(np.asarray(e) / max(float(np.percentile(e, 99)), 1e-6))
    envs = np.concatenate([fit(env(res.envmap), 128)[:, :, :] .repeat(1, 0)[:128], fit(env(gt.env_video), 128)], 1)
    img = np.concatenate(rows, 0)
    img[:128, 768 - 256:768] = img[:128, 768 - 256:768]
    write_image(path, img)
    write_image(path.with_name(path.stem + "_env.png"), envs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fabrics", default=",".join(FABRICS), help="comma-separated fabric kinds")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--start", type=int, default=0, help="simulated frames dropped before frame 0 (> 0: frame 0 "
                    "is billowed, not flat)")
    ap.add_argument("--motion", choices=["saft", "newton"], default="saft",
                    help="the cloth's simulator: saft's own on the template's mesh, or Newton's on a finer one")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of the videos")
    ap.add_argument("--eval-spp", type=int, default=64, help="samples per pixel of the relit novel views")
    ap.add_argument("--root", default="/tmp/saft-appearance-bench")
    ap.add_argument("--profile", choices=["cpu", "cuda", "paper"], default="cpu")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="where phase 3 and the relit views run (Mitsuba llvm_ad_rgb or cuda_ad_rgb); the scenes, "
                         "phase 1 and saft's motion are made on the CPU (or taken from --root's cache)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override an AppearanceConfig field (TOML value), e.g. --set epochs=200 (repeatable)")
    ap.add_argument("--own-motion", action="store_true", help="add the row of phase 3 on saft's own motion (its texture + shape run cached under --root)")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--no-true-motion", action="store_true", help="skip the row of phase 3 on the true motion")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (run.threads; 0 = automatic)")
    ap.add_argument("--json", default=None, help="write the rows to this file")
    ap.add_argument("--save-maps", default=None, help="write estimated | true maps per fabric into this folder")
    args = ap.parse_args(argv)

    base = {"cpu": cpu_profile, "cuda": cuda_profile, "paper": paper_profile}[args.profile]()
    cfg = AppearanceConfig.from_dict(merge_overrides(base.to_dict(), args.set), "--set")
    cfg.validate()
    root = Path(args.root)
    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for fabric in args.fabrics.split(","):
        spec = AppearanceSceneSpec(fabric=fabric, frames=args.frames, width=args.width, height=args.height,
                                   spp=args.spp, start=args.start, motion=args.motion)
        name = (f"{fabric}_{args.frames}f_{args.width}x{args.height}" + (f"_s{args.start}" if args.start else "")
                + ("" if args.motion == "saft" else f"_{args.motion}"))
        t0 = time.perf_counter()
        scene_dir = write_appearance_scene(root / "scenes" / name, spec)
        scene = load_scene(scene_dir)
        gt = read_appearance_ground_truth(scene_dir)
        truth = true_geometry(scene_dir, scene.template)     # scores: the relit views' geometry
        verts = true_motion_on_template(scene_dir)           # the "true motion" phase 3 is fitted on
        texture = phase1_texture(scene_dir, root / "results" / f"{name}-texture", args.threads)
        print(f"[{fabric}] scene + phase 1: {time.perf_counter() - t0:.0f} s", flush=True)
        if not args.no_baseline:
            rows.append({"fabric": fabric, **row("texture only", texture_baseline(texture), gt, scene, truth,
                                                 args.eval_spp, device=args.device)})
        rgb, mask = scene.frames.load()
        if not args.no_true_motion:
            res = fit_appearance(verts, scene.template.triangles, scene.template.uvs, scene.camera, rgb, mask, cfg,
                                 init_texture=texture, device=args.device)
            rows.append({"fabric": fabric, **row("phase 3, true motion", (res.diffuse, res.roughness, res.metallic),
                                                 gt, scene, truth, args.eval_spp, (res.seconds, res.cpu_seconds),
                                                 args.device),
                         "materials": res.materials})
            if args.save_maps:
                save_comparison(Path(args.save_maps) / f"{name}.png", res, gt, texture)
        if args.own_motion:
            positions, own_texture, cd2 = own_motion(scene_dir, root / "results" / f"{name}-shape", args.threads)
            own = fit_appearance(positions, scene.template.triangles, scene.template.uvs, scene.camera, rgb, mask,
                                 cfg, init_texture=own_texture, device=args.device)
            rows.append({"fabric": fabric, **row("phase 3, saft motion", (own.diffuse, own.roughness, own.metallic),
                                                 gt, scene, truth, args.eval_spp, (own.seconds, own.cpu_seconds),
                                                 args.device),
                         "shape_cd2": cd2, "materials": own.materials})
        for r in rows[-3:]:
            if r["fabric"] == fabric:
                print(json.dumps(r), flush=True)

    print(f"\nappearance benchmark: {args.frames} frames of {args.width}x{args.height} (start {args.start}, "
          f"motion {args.motion}), "
          f"video {args.spp} spp, "
          f"relit views {args.eval_spp} spp, profile {cfg.profile} on {args.device}, overrides {args.set or 'none'}")
    print("| fabric | method | diffuse PSNR (dB) | roughness MAE | metallic MAE | relit PSNR video light (dB) | "
          "relit PSNR unseen light (dB) | fit wall (s) | fit CPU (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        method = r["method"] + (f" (shape CD2 {r['shape_cd2']:.2f})" if "shape_cd2" in r else "")
        print(f"| {r['fabric']} | {method} | {r['diffuse_psnr_db']:.2f} | {r['roughness_mae']:.3f} | "
              f"{r['metallic_mae']:.3f} | {r['relit_video_psnr_db']:.2f} | {r['relit_unseen_psnr_db']:.2f} | "
              f"{r['fit_wall_s']:.0f} | {r['fit_cpu_s']:.0f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "config": cfg.to_dict(), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
