"""How far the point tracks drift from the true projections of the ground-truth vertices.

    python benchmarks/bench_tracks.py [--scenes-dir DIR] [--only a,b,c] [--radii 0,3] [--frames 5,10,20,29]
                                      [--jump-ratios 0,8] [--drifts 0,0.02]
    python benchmarks/bench_tracks.py --scenes-dir /tmp/saft-scenes/independent \
        --only flag_independent_pinned,gust_side_independent_pinned --radii 2 --jump-ratios 8 --drifts 0,0.02

On the benchmark scenes (saft.synthetic.benchmark_scenes, generated into --scenes-dir when missing; the
pinned and unpinned folders share one video, so the pinned one is used), computes the shape phase's
vertex tracks (saft.reconstruct.tracks) for each re-anchoring radius in --radii (0 = chained flow only) and
prints, per scene and frame, the median and 90th percentile of |track − projection of the ground-truth
vertex| over the still-valid tracks, and their coverage, for each colour-jump ratio in --jump-ratios
(shape.track_jump_ratio; 0 = off) and chromaticity drift in --drifts (shape.track_drift; 0 = off). A name in
--only that names a scene folder (the independent-simulator scenes, whose 40 × 40 ground truth is resampled
onto the 25 × 25 template's material grid) is used as it is. The last lines are `tracks_p90_px_last_frame_<radius>[_jump<ratio>][_drift<d>]=<median
over scenes>` for each radius and ratio.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from saft.reconstruct.tracks import compute_vertex_tracks, project
from saft.render import get_rasterizer, render_cloth
from saft.scene import load_scene
from saft.synthetic.benchmark_scenes import SCENARIOS, BenchSceneSpec, write_benchmark_scenes
from saft.synthetic.independent_scenes import resample_grid


def scene_tracks_error(folder: Path, radius: float, fb_threshold: float = 1.0, jump_ratio: float = 0.0,
                       drift: float = 0.0) -> dict:
    scene = load_scene(folder)
    camera = scene.working_camera(1.0)
    rgb, mask = scene.working_frames(1.0).load()
    template = torch.as_tensor(scene.template.vertices, dtype=torch.float64)
    tri = torch.as_tensor(scene.template.triangles, dtype=torch.int32)
    uvs = torch.as_tensor(scene.template.uvs, dtype=torch.float32)
    depth0 = render_cloth(template[None].float(), tri, uvs, torch.full((8, 8, 3), 0.5), camera,
                          rasterizer=get_rasterizer("torch", "cpu")).depth[0]
    t0 = time.perf_counter()
    tracks = compute_vertex_tracks(torch.as_tensor(rgb), torch.as_tensor(mask), template, camera, depth0,
                                   fb_threshold, reanchor_radius=radius, jump_ratio=jump_ratio, drift=drift)
    seconds = time.perf_counter() - t0
    gt = np.load(folder / "gt_vertices.npy")
    if gt.shape[1] != template.shape[0]:     # a finer ground-truth grid: its points at the template's vertices
        n, m = round(gt.shape[1] ** 0.5), round(template.shape[0] ** 0.5)
        gt = np.stack([resample_grid(g.reshape(n, n, 3), m) for g in gt])
    gt = torch.as_tensor(gt, dtype=torch.float64)
    uv_true, _ = project(gt, camera)
    err = (tracks.points - uv_true).norm(dim=-1).numpy()
    valid = tracks.valid.numpy()
    rows = []
    for t in range(err.shape[0]):
        e = err[t][valid[t]]
        rows.append((float(np.median(e)) if e.size else float("nan"),
                     float(np.percentile(e, 90)) if e.size else float("nan"), float(valid[t].mean())))
    every = err[valid]
    return {"rows": rows, "seconds": seconds, "track_frames": int(every.size),
            "over_4px": float((every > 4).mean()) if every.size else float("nan")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes-dir", type=Path, default=Path("/tmp/saft-bench-scenes"))
    p.add_argument("--only", default=",".join(SCENARIOS), help="scenarios (a, b, c)")
    p.add_argument("--radii", default="0,3", help="re-anchoring radii in pixels (0 = chained flow only)")
    p.add_argument("--frames", default="5,10,20,29", help="frames to print (clipped to the video)")
    p.add_argument("--jump-ratios", default="0", help="colour-jump ratios (shape.track_jump_ratio; 0 = off)")
    p.add_argument("--drifts", default="0", help="chromaticity drifts (shape.track_drift; 0 = off)")
    args = p.parse_args()
    scenarios = [s for s in args.only.split(",") if s]
    generated = [s for s in scenarios if s in SCENARIOS]
    if generated:
        write_benchmark_scenes(args.scenes_dir, replace(BenchSceneSpec()), generated)
    settings = [(float(r), float(j), float(d)) for r in args.radii.split(",") for j in args.jump_ratios.split(",")
                for d in args.drifts.split(",")]
    last_p90: dict[tuple[float, float, float], list[float]] = {k: [] for k in settings}
    for s in scenarios:
        folder = args.scenes_dir / (f"{s}_pinned" if s in SCENARIOS else s)
        for r, j, d in settings:
            res = scene_tracks_error(folder, r, jump_ratio=j, drift=d)
            rows = res["rows"]
            frames = [f for f in (int(x) for x in args.frames.split(",")) if f < len(rows)] or [len(rows) - 1]
            cells = "  ".join(f"f{f}: {rows[f][0]:.2f}/{rows[f][1]:.2f} px ({rows[f][2]:.2f})" for f in frames)
            print(f"{s} radius {r:g} jump {j:g} drift {d:g}: {cells}; all frames: {res['track_frames']} "
                  f"track-frames, {100 * res['over_4px']:.1f} % > 4 px  [{res['seconds']:.1f} s]", flush=True)
            last_p90[(r, j, d)].append(rows[-1][1])
    for r, j, d in settings:
        suffix = (f"_jump{j:g}" if j > 0 else "") + (f"_drift{d:g}" if d > 0 else "")
        print(f"tracks_p90_px_last_frame_{r:g}{suffix}={float(np.nanmedian(last_p90[(r, j, d)])):.3f}")


if __name__ == "__main__":
    main()
