"""Synthetic appearance benchmark (like the paper's SR scenes): known maps + env map → estimate → compare.

A hanging 16×16-quad sheet moved by the project's simulator (``saft.physics.rollout``, top row pinned,
travelling wind; ``--motion waves`` uses a procedural stand-in) is rendered through Mitsuba with known
diffuse/roughness/metallic maps and a coloured environment map at many spp. Phase 3 then estimates the
appearance from every frame except the held-out ones (every 4th), and we report

* PSNR (sRGB, inside the mask) of re-renders on the held-out frames and on the training frames,
* PSNR of a novel view (camera turned 45° around the cloth) of the middle frame,
* the RMSE of the linear diffuse map after the best global scale (the diffuse/light ambiguity allows one),
* the run time of the fit.

Case (a) fits with the true motion; case (b) with the motion that saft's texture + shape phases reconstruct
from the same renders (``reconstruct_motion_hook``; or pass ``--estimated-motion FILE.npy``).

    python benchmarks/bench_appearance.py                 # CPU profile, 20 frames, 200×200
    python benchmarks/bench_appearance.py --profile paper --device cuda
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
import torch.nn.functional as F

from saft.appearance import AppearanceResult, fit_appearance, render_appearance
from saft.appearance.config import cpu_profile, paper_profile
from saft.synthetic.appearance import SyntheticScene, grid_sheet, make_scene, render_targets, wave_motion
from saft.scene.camera import orbit_camera


def physics_motion(verts0: np.ndarray, quads: np.ndarray, n_frames: int, frame_dt: float = 0.04) -> np.ndarray:
    """The sheet pinned along its top row, pushed by a travelling gust along z (saft.physics.rollout)."""
    from saft.physics import ClothTopology, PhysicsParams, rollout

    topo = ClothTopology.from_quads(verts0, quads)
    V = verts0.shape[0]
    top = np.nonzero(np.isclose(verts0[:, 1], verts0[:, 1].max()))[0]
    params = PhysicsParams.default(n_frames, V)
    y = torch.as_tensor(verts0[:, 1])
    x = torch.as_tensor(verts0[:, 0])
    hang = (y.max() - y) / (y.max() - y.min())
    with torch.no_grad():
        for k in range(n_frames - 1):
            t = k * frame_dt
            params.a_vert[k, :, 2] = 6.0 * torch.sin(2 * math.pi * (0.8 * hang + 0.6 * x - 1.2 * t)) * hang
    out = rollout(topo, torch.as_tensor(verts0), params=params, num_frames=n_frames, frame_dt=frame_dt, pinned=top)
    return out.detach().cpu().numpy()


def reconstruct_motion_hook(scene: SyntheticScene, frame_dt: float = 0.04) -> np.ndarray:
    """Case (b): the motion that `saft reconstruct` (texture + shape phases, default settings, no pinned
    vertices given) recovers from the Mitsuba renders scene.rgb / scene.mask and the frame-0 mesh."""
    import tempfile
    from pathlib import Path

    from saft.reconstruct import reconstruct
    from saft.reconstruct.config import load_saft_config
    from saft.scene import FrameSequence, QuadMesh, Scene, load_scene
    from saft.scene.native import write_native_scene

    work = Path(tempfile.mkdtemp(prefix="saft-bench-appearance-"))
    template = QuadMesh(scene.vertices[0], scene.quads, scene.uvs)
    h, w = scene.rgb.shape[1:3]
    native = Scene(name="appearance-bench", template=template, camera=scene.camera,
                   frames=FrameSequence((), None, w, h), frame_dt=frame_dt)
    write_native_scene(work / "scene", native, scene.rgb, scene.mask)
    cfg = load_saft_config(None, ['run.device="cpu"', "appearance.enabled=false"])
    t0 = time.perf_counter()
    outcome = reconstruct(load_scene(work / "scene"), cfg, work / "result", quiet=True)
    err = np.linalg.norm(outcome.positions - scene.vertices, axis=-1).mean()
    print(f"(b) shape reconstruction: {time.perf_counter() - t0:.0f} s, mean vertex error {err * 1000:.1f} mm "
          f"(static template {np.linalg.norm(scene.vertices[:1] - scene.vertices, axis=-1).mean() * 1000:.1f} mm)")
    return outcome.positions


def masked_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    m = mask[..., None]
    mse = float(((pred - target) ** 2 * m).sum() / max(float(m.sum()) * 3, 1e-8))
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def diffuse_error(est: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    """(RMSE after the best global scale, that scale, RMSE without scaling) of linear diffuse maps."""
    e = torch.as_tensor(est).permute(2, 0, 1)[None]
    e = F.interpolate(e, size=gt.shape[:2], mode="bilinear", align_corners=False)[0].permute(1, 2, 0).numpy()
    s = float((e * gt).sum() / max(float((e * e).sum()), 1e-12))
    return float(np.sqrt(((s * e - gt) ** 2).mean())), s, float(np.sqrt(((e - gt) ** 2).mean()))


def evaluate(label: str, res: AppearanceResult, sc: SyntheticScene, train: np.ndarray, held: np.ndarray,
             novel: tuple, device: str, spp: int) -> dict:
    imgs = render_appearance(res, sc.vertices, sc.triangles, sc.uvs, sc.camera, spp=spp, device=device)
    cam45, frame, rgb45, mask45 = novel
    img45 = render_appearance(res, sc.vertices[frame], sc.triangles, sc.uvs, cam45, spp=spp, device=device)
    d_rmse, d_scale, d_raw = diffuse_error(res.diffuse, sc.diffuse)
    return {
        "case": label,
        "psnr_held": masked_psnr(imgs[held], sc.rgb[held], sc.mask[held]),
        "psnr_train": masked_psnr(imgs[train], sc.rgb[train], sc.mask[train]),
        "psnr_novel": masked_psnr(img45, rgb45, mask45),
        "diffuse_rmse": d_rmse, "diffuse_scale": d_scale, "diffuse_rmse_raw": d_raw,
        "seconds": res.seconds, "cpu_seconds": res.cpu_seconds,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--size", type=int, default=200, help="image side in pixels")
    ap.add_argument("--profile", choices=["cpu", "paper"], default=None, help="default: cpu on CPU, paper on CUDA")
    ap.add_argument("--epochs", type=int, default=None)
    ap.add_argument("--maps", choices=["decoder", "texels"], default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--gt-spp", type=int, default=256, help="samples per pixel of the ground-truth renders")
    ap.add_argument("--eval-spp", type=int, default=64)
    ap.add_argument("--motion", choices=["physics", "waves"], default="physics")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override an AppearanceConfig field, e.g. --set lr_texels=0.05 (repeatable)")
    ap.add_argument("--estimated-motion", default=None, help="(F, V, 3) .npy of reconstructed motion: case (b)")
    ap.add_argument("--no-reconstruction", action="store_true", help="skip case (b) (reconstructed motion)")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    sc = make_scene(n_frames=args.frames, image_size=args.size, render=False, device=args.device)
    verts0, quads, _ = grid_sheet(16)
    motion_used = args.motion
    if args.motion == "physics":
        try:
            sc.vertices = physics_motion(verts0, quads, args.frames)
        except Exception as exc:  # the simulator is optional here; say so and fall back
            print(f"saft.physics rollout failed ({type(exc).__name__}: {exc}); using procedural waves")
            sc.vertices, motion_used = wave_motion(verts0, args.frames), "waves"
    sc.rgb, sc.mask = render_targets(sc, args.gt_spp, device=args.device)
    frame = args.frames // 2
    centre = sc.vertices[frame].mean(axis=0)
    cam45 = orbit_camera(sc.camera, centre, 45.0)
    rgb45, mask45 = render_targets(sc, args.gt_spp, device=args.device, camera=cam45,
                                   vertices=sc.vertices[frame:frame + 1])
    novel = (cam45, frame, rgb45[0], mask45[0])
    t_data = time.perf_counter() - t0

    idx = np.arange(args.frames)
    held = idx[idx % 4 == 3]
    train = idx[idx % 4 != 3]
    profile = args.profile or ("cpu" if args.device == "cpu" else "paper")
    cfg = cpu_profile() if profile == "cpu" else paper_profile()
    if args.epochs:
        cfg.epochs = args.epochs
    if args.maps:
        cfg.maps = args.maps
    for item in args.set:
        key, _, value = item.partition("=")
        old = getattr(cfg, key)
        setattr(cfg, key, type(old)(value) if not isinstance(old, bool) else value.lower() in ("1", "true", "yes"))
    cfg.validate()

    rows = []
    init = AppearanceResult(np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8), 0.5, np.float32),
                            np.full((8, 8), 0.5, np.float32), np.full((cfg.env_height, cfg.env_width, 3), 0.5,
                                                                        np.float32), [], cfg)
    rows.append(evaluate("initial grey", init, sc, train, held, novel, args.device, args.eval_spp))

    def run(label, fit_vertices):
        res = fit_appearance(fit_vertices[train], sc.triangles, sc.uvs, sc.camera, sc.rgb[train], sc.mask[train],
                             cfg, device=args.device)
        rows.append(evaluate(label, res, sc, train, held, novel, args.device, args.eval_spp))

    run("(a) true motion", sc.vertices)
    if args.estimated_motion:
        est = np.load(args.estimated_motion)
    elif args.motion == "physics" and motion_used == "physics" and not args.no_reconstruction:
        est = reconstruct_motion_hook(sc)
    else:
        est = None
    if est is not None:
        run("(b) reconstructed motion", np.asarray(est, dtype=np.float64))

    print(f"synthetic appearance benchmark: {args.frames} frames ({len(train)} fit, {len(held)} held out), "
          f"{args.size}x{args.size} px, motion={motion_used}, device={args.device}, profile={cfg.profile} "
          f"(epochs={cfg.epochs}, frames/epoch={cfg.frames_per_epoch or 'all'}, scale={cfg.image_scale}, "
          f"maps={cfg.maps} " + (f"{cfg.tile_size}px tiles" if cfg.maps == "decoder" else f"{cfg.texel_size}px") + f", spp={cfg.spp}, loss={cfg.loss}); "
          f"ground truth at {args.gt_spp} spp, evaluation at {args.eval_spp} spp; data {t_data:.0f} s")
    print("| case | PSNR held-out (dB) | PSNR train (dB) | PSNR novel 45° (dB) | diffuse RMSE (scaled) | scale | "
          "diffuse RMSE (raw) | fit wall (s) | fit CPU (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['psnr_held']:.2f} | {r['psnr_train']:.2f} | {r['psnr_novel']:.2f} | "
              f"{r['diffuse_rmse']:.4f} | {r['diffuse_scale']:.3f} | {r['diffuse_rmse_raw']:.4f} | "
              f"{r['seconds']:.0f} | {r['cpu_seconds']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
