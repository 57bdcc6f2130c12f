"""Where a reconstruction of an independent-simulator scene goes wrong: depth or image plane, data or optimiser.

    python benchmarks/diagnose_independent.py SCENE_DIR RESULT_DIR [--frames 3,9,18,30] [--drift 0]

SCENE_DIR: a scene of saft.synthetic.independent_scenes (its 40 × 40 ground truth is resampled onto the
25 × 25 template's material grid, so every template vertex has a true position); RESULT_DIR: a saft result
of it (meshes/, texture.png). Per frame, in the working camera:

- the RMS error of the vertices along the camera's z axis (depth) and across it (lateral), cm, and the
  median / 90th percentile of the distance between their projections, px;
- the shape phase's image and silhouette losses (render_cloth with the result's texture, unlit) of the
  ground truth on the template and of the reconstruction: where the truth scores lower, the data term
  prefers it and the optimiser did not reach it;
- the track loss (× shape.lambda_track, the default tracks with shape.track_drift = --drift) of both.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from saft.io_utils import read_image
from saft.reconstruct.config import ShapeConfig
from saft.reconstruct.losses import image_loss, silhouette_loss
from saft.reconstruct.tracks import compute_vertex_tracks, project, track_loss
from saft.render import get_rasterizer, render_cloth
from saft.scene import load_scene, read_obj
from saft.synthetic.independent_scenes import resample_grid


def truth_on_template(folder: Path, n_template: int) -> np.ndarray:
    """(F, V, 3) ground-truth positions at the template's vertices."""
    gt = np.load(folder / "gt_vertices.npy")
    if gt.shape[1] == n_template:
        return gt
    n, m = round(gt.shape[1] ** 0.5), round(n_template ** 0.5)
    return np.stack([resample_grid(g.reshape(n, n, 3), m) for g in gt])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("result", type=Path)
    p.add_argument("--frames", default="3,9,18,30")
    p.add_argument("--drift", type=float, default=0.0, help="shape.track_drift of the tracks scored")
    args = p.parse_args()
    scene = load_scene(args.scene)
    cam = scene.working_camera(1.0)
    rgb, mask = scene.working_frames(1.0).load()
    tpl = scene.template
    tri = torch.as_tensor(tpl.triangles, dtype=torch.int32)
    uvs = torch.as_tensor(tpl.uvs, dtype=torch.float32)
    ras = get_rasterizer("torch", "cpu")
    truth = torch.as_tensor(truth_on_template(args.scene, len(tpl.vertices)))
    recon = torch.stack([torch.as_tensor(read_obj(args.result / "meshes" / f"frame_{t:03d}.obj").vertices,
                                         dtype=torch.float64) for t in range(len(truth))])
    texture = torch.as_tensor(read_image(args.result / "texture.png"), dtype=torch.float32)
    cfg = ShapeConfig()
    template = torch.as_tensor(tpl.vertices, dtype=torch.float64)
    depth0 = render_cloth(template[None].float(), tri, uvs, texture, cam, rasterizer=ras).depth[0]
    tracks = compute_vertex_tracks(torch.as_tensor(rgb), torch.as_tensor(mask), template, cam, depth0,
                                   cfg.track_fb_threshold, cfg.track_reanchor_radius, cfg.track_jump_ratio,
                                   cfg.track_jump_floor, args.drift)
    R = torch.as_tensor(cam.world_to_camera[:3, :3], dtype=torch.float64)
    print("frame  depth_cm lateral_cm  px_med px_p90 | image truth/recon  silhouette truth/recon | "
          "track truth/recon")
    for t in (int(f) for f in args.frames.split(",") if int(f) < len(truth)):
        d = (recon[t] - truth[t]) @ R.T
        depth = 100 * float(d[:, 2].pow(2).mean().sqrt())
        lateral = 100 * float(d[:, :2].pow(2).sum(-1).mean().sqrt())
        px = (project(recon[t], cam)[0] - project(truth[t], cam)[0]).norm(dim=-1).numpy()
        losses = []
        for v in (truth[t], recon[t]):
            out = render_cloth(v[None].float(), tri, uvs, texture, cam, rasterizer=ras)
            losses.append((float(image_loss(out.rgb, torch.as_tensor(rgb[t:t + 1]))),
                           float(silhouette_loss(out.mask, torch.as_tensor(mask[t:t + 1]))),
                           abs(cfg.lambda_track * float(track_loss(v[None], tracks, cam, cfg.track_huber, t)))))
        (ig, sg, tg), (ir, sr, tr) = losses
        print(f"{t:5d}  {depth:8.2f} {lateral:10.2f}  {np.median(px):6.1f} {np.percentile(px, 90):6.1f} | "
              f"{ig:.5f} / {ir:.5f}      {sg:.5f} / {sr:.5f}       | {tg:.4f} / {tr:.4f}")


if __name__ == "__main__":
    main()
