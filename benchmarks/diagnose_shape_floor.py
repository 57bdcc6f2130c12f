"""How low CD2 can a mesh of the result's own topology go? A diagnostic for issue 29's R1 target.

For each frame, the result's mesh is moved towards the ground-truth point cloud (Adam on the vertices, CD2 on
random surface samples, the edge lengths held near the result's frame-0 lengths so that the cloth stays a
cloth), then scored exactly as `saft evaluate` scores (same surface samples, same seed). The gap between the
result's CD2 and this floor is what inference loses; the floor itself is what the mesh resolution and the
sensor's noise allow. No image is used: this is an upper bound for any method on this topology.

CD2 does not see a vertex sliding along the surface, so the free floor's meshes do not keep the result's
material points (their texture lands elsewhere). With `--along-rays` each vertex may only move along its own
camera ray: the projections, and so the rendered image, stay the result's; what that floor leaves is the
error in depth alone.

    python3 benchmarks/diagnose_shape_floor.py RESULT_DIR [--scene ../shared/data/phi_sft/data/scenes/R1.json]
        [--frames 0,10,20] [--every 5] [--edge-weight 10] [--steps 300] [--along-rays] [--json OUT.json]
        [--save DIR]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from saft.evaluate import ground_truth_spec_for
from saft.evaluate.evaluate import read_result_mesh
from saft.evaluate.ground_truth import load_ground_truth_frames
from saft.evaluate.metrics import CD2, frame_metrics, frame_rng
from saft.scene import load_scene

SAMPLES = 8000  # surface samples and GT points per optimisation step (the score itself uses all GT points)


def scored_cd2(vertices: np.ndarray, triangles: np.ndarray, gt: np.ndarray, frame: int) -> float:
    """CD2 (1e-4 m²) of one frame exactly as `saft evaluate` scores it (seed 0)."""
    return frame_metrics(vertices, triangles, gt, frame_rng(0, frame))[CD2]


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def fit_to_cloud(vertices: np.ndarray, triangles: np.ndarray, gt: np.ndarray, rest: torch.Tensor,
                 edges: torch.Tensor, edge_weight: float, steps: int, seed: int,
                 rays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The vertices moved to minimise sampled CD2 + edge_weight · 1e-4 · mean relative strain²; with rays
    ((V, 3) unit directions), each only along its own ray."""
    rng = np.random.default_rng(seed)
    start = torch.as_tensor(vertices)
    step = torch.zeros(len(vertices) if rays is not None else vertices.shape, dtype=torch.float64, requires_grad=True)
    ray = None if rays is None else torch.as_tensor(rays)
    gt_t = torch.as_tensor(gt, dtype=torch.float64)
    tris = torch.as_tensor(triangles)
    gt_tree = cKDTree(gt)
    optimiser = torch.optim.Adam([step], lr=5e-4)
    for _ in range(steps):
        x = start + (step if ray is None else step[:, None] * ray)
        corners = x[tris]
        area = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=1)
        area = area.detach().numpy()
        which = rng.choice(len(triangles), SAMPLES, p=area / area.sum())
        r = rng.random((SAMPLES, 2))
        s = np.sqrt(r[:, 0])
        weights = torch.as_tensor(np.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], 1))
        samples = (corners[which] * weights[:, :, None]).sum(1)
        picked = gt_t[rng.choice(len(gt), min(SAMPLES, len(gt)), replace=False)]
        nearest_sample = cKDTree(samples.detach().numpy()).query(picked.numpy())[1]
        nearest_gt = gt_tree.query(samples.detach().numpy())[1]
        loss = (((picked - samples[nearest_sample]) ** 2).sum(1).mean()
                + ((samples - gt_t[nearest_gt]) ** 2).sum(1).mean())
        lengths = (x[edges[:, 0]] - x[edges[:, 1]]).norm(dim=1)
        strain = (lengths - rest) / rest
        loss = loss + edge_weight * 1e-4 * (strain ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return x.detach().numpy(), strain.detach().abs().numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result", type=Path)
    ap.add_argument("--scene", default="../shared/data/phi_sft/data/scenes/R1.json")
    ap.add_argument("--frames", default=None, help="comma-separated frame indices (default: every --every)")
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--edge-weight", type=float, default=10.0)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--along-rays", action="store_true", help="move each vertex only along its camera ray")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--save", type=Path, default=None, help="write each frame's moved vertices as floor_FFF.npy")
    a = ap.parse_args()
    torch.set_num_threads(1)
    scene = load_scene(a.scene)
    gts = load_ground_truth_frames(ground_truth_spec_for(scene))
    w2c = scene.camera.world_to_camera
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    files = sorted((a.result / "meshes").glob("frame_*.obj"))
    frames = ([int(f) for f in a.frames.split(",")] if a.frames else
              sorted(set(range(0, len(files), a.every)) | {len(files) - 1}))
    first = read_result_mesh(files[0])
    triangles = first.triangles
    edges = torch.as_tensor(mesh_edges(triangles))
    v0 = torch.as_tensor(first.vertices)
    rest = (v0[edges[:, 0]] - v0[edges[:, 1]]).norm(dim=1)
    rows = []
    for f in frames:
        gt, vertices = gts[f], read_result_mesh(files[f]).vertices
        before = scored_cd2(vertices, triangles, gt, f)
        rays = None
        if a.along_rays:
            rays = vertices - centre
            rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        moved, strain = fit_to_cloud(vertices, triangles, gt, rest, edges, a.edge_weight, a.steps, seed=f, rays=rays)
        if a.save:
            a.save.mkdir(parents=True, exist_ok=True)
            np.save(a.save / f"floor_{f:03d}.npy", moved)
        floor = scored_cd2(moved, triangles, gt, f)
        rows.append(dict(frame=f, cd2=before, floor=floor, strain_median=float(np.median(strain)),
                         strain_p95=float(np.percentile(strain, 95))))
        print(f"frame {f:3d}  CD2 {before:.3f}  floor {floor:.3f}  strain median {rows[-1]['strain_median']:.3f} "
              f"p95 {rows[-1]['strain_p95']:.3f}", flush=True)
    print(f"mean over {len(rows)} frames: CD2 {np.mean([r['cd2'] for r in rows]):.3f}, "
          f"floor {np.mean([r['floor'] for r in rows]):.3f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
