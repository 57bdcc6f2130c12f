"""Is a texture fitted on several frames a better diffuse start than phase 1's T of frame 0? (issue 28)

For each cached appearance benchmark scene (bench_appearance.py's --root layout: scenes/<name>, the
phase-1 texture in results/<name>-texture, saft's own shape run in results/<name>-shape), the phase-1
texture is refitted on N frames (saft.appearance.texture_frames) through the TRUE meshes (the scene's
motion on the template) and through SAFT's meshes, and each texture is scored as the texture-only diffuse
(saft.evaluate.appearance.map_metrics: PSNR after the best per-channel scale), beside phase 1's T.
Nothing is written under --root.

    PYTHONPATH=src OMP_NUM_THREADS=1 nice -n 10 python3 benchmarks/bench_texture_frames.py --counts 4,8,16 --json J
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from saft.appearance.texture_frames import choose_texture_frames, fit_texture_frames
from saft.appearance.guided import material_clusters, smooth_within_clusters
from saft.appearance.params import srgb_to_linear
from saft.evaluate.appearance import map_metrics, read_appearance_ground_truth, texture_baseline, uv_coverage
from saft.io_utils import read_image
from saft.scene import load_scene
from saft.scene.mesh import read_obj
from saft.synthetic.appearance import true_motion_on_template


def diffuse_psnr(texture_srgb, gt, coverage) -> float:
    return float(map_metrics(*texture_baseline(texture_srgb), gt, coverage)["diffuse_psnr_db"])


def smooth_psnr(texture_srgb, gt, coverage) -> float:
    """The same for the texture as phase 3 starts from it before any detail comes back: linear, blurred
    inside its colour clusters (GuidedMaps' T_s, the CPU profile's clusters and σ)."""
    lin = srgb_to_linear(np.asarray(texture_srgb, dtype=np.float32))
    smooth = smooth_within_clusters(lin, material_clusters(lin, 6, 0), 4.0)
    return float(map_metrics(smooth, *texture_baseline(texture_srgb)[1:], gt, coverage)["diffuse_psnr_db"])


def shading_drift(texture_srgb, reference_srgb, sigma: float = 8.0) -> float:
    """RMS over texels and channels of log(blur(T) / blur(T_ref)) (linear, Gaussian σ texels): how far the
    refitted texture's shading has moved from frame 0's."""
    from scipy.ndimage import gaussian_filter
    blur = lambda a: gaussian_filter(srgb_to_linear(np.asarray(a, np.float32)).astype(np.float64), (sigma, sigma, 0))
    r = np.log(np.maximum(blur(texture_srgb), 1e-4) / np.maximum(blur(reference_srgb), 1e-4))[16:-16, 16:-16]
    return float(np.sqrt((r ** 2).mean()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="/tmp/saft-appearance-bench")
    ap.add_argument("--suffix", default="_32f_320x240", help="scene name = fabric + suffix")
    ap.add_argument("--fabrics", default="plaid,print,cotton,satin,lame")
    ap.add_argument("--counts", default="4,8,16")
    ap.add_argument("--choice", default="first", help="comma-separated: first, spread, trusted")
    ap.add_argument("--meshes", default="true,saft")
    ap.add_argument("--epochs", type=int, default=100)
    ap.add_argument("--lr", type=float, default=0.02)
    ap.add_argument("--gain-grid", type=int, default=4)
    ap.add_argument("--shift-grid", type=int, default=0, help="> 0: each frame's mesh registered by a grid of pixel shifts")
    ap.add_argument("--lr-shift", type=float, default=0.05)
    ap.add_argument("--keep-shading", type=float, default=0.0, help="> 0: T's shading put back to frame 0's (σ texels)")
    ap.add_argument("--register-epochs", type=int, default=0, help="first epochs: gains and shifts only")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    root, rows = Path(args.root), []
    for fabric in args.fabrics.split(","):
        name = fabric + args.suffix
        scene_dir = root / "scenes" / name
        scene = load_scene(scene_dir)
        gt = read_appearance_ground_truth(scene_dir)
        coverage = uv_coverage(scene.template.triangles, scene.template.uvs, gt.roughness.shape[0])
        rgb, mask = scene.frames.load()
        texture = read_image(root / "results" / f"{name}-texture" / "texture.png")[..., :3]
        base = diffuse_psnr(texture, gt, coverage)
        rows.append({"fabric": fabric, "meshes": "-", "choice": "-", "n": 1, "psnr": base,
                     "psnr_smooth": smooth_psnr(texture, gt, coverage)})
        print(json.dumps(rows[-1]), flush=True)
        meshes = {"true": lambda: true_motion_on_template(scene_dir),
                  "saft": lambda: np.stack([read_obj(p).vertices for p in
                                            sorted((root / "results" / f"{name}-shape" / "meshes").glob("frame_*.obj"))])}
        for which in args.meshes.split(","):
            verts = meshes[which]()
            tri, uvs = scene.template.triangles, scene.template.uvs
            for choice in args.choice.split(","):
                for n in (int(c) for c in args.counts.split(",")):
                    frames = choose_texture_frames(choice, n, texture, verts, tri, uvs, scene.camera, rgb, mask)
                    t0, c0 = time.perf_counter(), time.process_time()
                    tex, gains, shifts, losses = fit_texture_frames(
                        verts, tri, uvs, scene.camera, rgb, mask, frames, texture, epochs=args.epochs, lr=args.lr,
                        gain_grid=args.gain_grid, shift_grid=args.shift_grid, lr_shift=args.lr_shift,
                        register_epochs=args.register_epochs, keep_shading=args.keep_shading)
                    rows.append({"fabric": fabric, "meshes": which, "choice": choice, "n": n, "frames": frames,
                                 "psnr": diffuse_psnr(tex, gt, coverage), "delta": diffuse_psnr(tex, gt, coverage) - base,
                                 "psnr_smooth": smooth_psnr(tex, gt, coverage),
                                 "shading_drift": shading_drift(tex, texture),
                                 "loss_first": losses[0], "loss_last": losses[-1],
                                 "gain_range": [float(gains.min()), float(gains.max())],
                                 "shift_px": float(np.abs(shifts).max()),
                                 "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0})
                    print(json.dumps(rows[-1]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
