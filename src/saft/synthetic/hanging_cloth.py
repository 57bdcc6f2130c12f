"""Synthetic scenes made with saft's own simulator and rasterizer (the demo and the end-to-end tests).

A square cloth hangs from its top edge in front of a camera and is blown by a gust: the ground truth is
the simulated motion, the video its textured rendering.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from saft.evaluate.metrics import sample_surface
from saft.io_utils import atomic_save_npy
from saft.physics import ClothTopology, PhysicsParams, rollout
from saft.render import render_cloth
from saft.scene.camera import look_at
from saft.scene.frames import FrameSequence
from saft.scene.mesh import QuadMesh
from saft.scene.native import write_native_scene
from saft.scene.scene import Scene


@dataclass(frozen=True)
class HangingClothSpec:
    grid: int = 16                 # vertices per side
    size: float = 0.4              # metres
    frames: int = 20
    frame_dt: float = 0.02
    image_size: int = 200          # square image, pixels
    focal: float = 380.0           # pixels
    eye: tuple[float, float, float] = (0.25, 0.08, 0.95)
    log10_Y: float = 2.6
    log10_B: float = -3.3
    log10_S: float = -3.6
    damping: float = 0.9
    gust: float = 20.0             # peak wind acceleration, m/s² (moves the hem by ~15 cm)
    texture_size: int = 256
    gt_points: int = 4000          # points sampled per frame for the ground-truth clouds
    seed: int = 0


def grid_template(n: int, size: float) -> QuadMesh:
    """An n×n-vertex square in the plane z = 0, x right, y up, centred at the origin; row 0 at the top."""
    s = np.linspace(-0.5, 0.5, n) * size
    xs, ys = np.meshgrid(s, s[::-1])
    verts = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel(), idx[:-1, :-1].ravel()], 1)
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(1, 0, n))
    return QuadMesh(verts, quads, np.stack([u.ravel(), v.ravel()], axis=1))


def procedural_texture(size: int, seed: int = 0) -> np.ndarray:
    """A colourful, non-repeating pattern (checks, stripes and blobs) that gives the image loss a signal."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    checks = ((np.floor(x * 8) + np.floor(y * 8)) % 2)
    tex = np.stack([0.25 + 0.5 * x, 0.3 + 0.4 * y, 0.7 - 0.4 * x * y], axis=2)
    tex = tex * (0.65 + 0.35 * checks[..., None])
    for _ in range(12):
        cx, cy, r = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0.03, 0.1)
        blob = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r * r))
        tex = tex * (1 - blob[..., None]) + rng.uniform(0, 1, 3) * blob[..., None]
    stripes = 0.5 + 0.5 * np.sin(2 * np.pi * (x * 3 + y * 17))
    tex *= (0.85 + 0.15 * stripes[..., None])
    return np.clip(tex, 0, 1).astype(np.float32)


def gust_accelerations(template: np.ndarray, frames: int, frame_dt: float, peak: float, seed: int) -> np.ndarray:
    """(frames-1, V, 3) wind accelerations: a gust along z (towards the camera side) with a lateral part,
    rising and falling in time and varying smoothly across the cloth."""
    rng = np.random.default_rng(seed)
    t = (np.arange(frames - 1) + 0.5) * frame_dt
    duration = max(frames - 1, 1) * frame_dt
    envelope = np.sin(np.pi * np.clip(t / (0.6 * duration), 0, 1)) ** 2
    x, y = template[:, 0], template[:, 1]
    span = np.ptp(template[:, :2], axis=0).max()
    phase = rng.uniform(0, 2 * np.pi, 2)
    spatial_z = 1.0 + 0.5 * np.sin(2 * np.pi * x / span + phase[0]) * np.cos(np.pi * y / span + phase[1])
    spatial_x = 0.3 * np.cos(np.pi * y / span)
    a = np.zeros((frames - 1, len(template), 3))
    a[:, :, 2] = peak * envelope[:, None] * spatial_z[None]
    a[:, :, 0] = peak * envelope[:, None] * spatial_x[None] * np.sin(2 * np.pi * t / duration)[:, None]
    return a


def make_hanging_cloth(spec: HangingClothSpec = HangingClothSpec(), device="cpu"):
    """Simulate and render the scene. Returns (scene without frames on disk, rgb (F,H,W,3), mask (F,H,W),
    ground-truth vertices (F,V,3), ground-truth point clouds [F × (P,3)])."""
    template = grid_template(spec.grid, spec.size)
    gravity = np.array([0.0, -9.81, 0.0])
    top_row = np.arange(spec.grid)
    f64 = dict(dtype=torch.float64, device=device)
    topo = ClothTopology.from_quads(template.vertices, template.quads, device=device, dtype=torch.float64)
    accel = gust_accelerations(template.vertices, spec.frames, spec.frame_dt, spec.gust, spec.seed)
    params = PhysicsParams(torch.tensor(spec.log10_Y, **f64), torch.tensor(spec.log10_B, **f64),
                           torch.tensor(spec.log10_S, **f64), torch.tensor(spec.damping, **f64),
                           torch.tensor(gravity, **f64), torch.tensor(accel, **f64))
    with torch.no_grad():
        x0 = torch.tensor(template.vertices, **f64)
        positions = rollout(topo, x0, None, params, num_frames=spec.frames, substeps=4, frame_dt=spec.frame_dt,
                            pinned=torch.as_tensor(top_row, device=device)).cpu().numpy()

    K = np.array([[spec.focal, 0, (spec.image_size - 1) / 2], [0, spec.focal, (spec.image_size - 1) / 2], [0, 0, 1]])
    camera = look_at(spec.eye, (0.0, -0.03, 0.0), (0.0, 1.0, 0.0), K, spec.image_size, spec.image_size)
    texture = procedural_texture(spec.texture_size, spec.seed)
    with torch.no_grad():
        out = render_cloth(torch.tensor(positions, dtype=torch.float32, device=device),
                           torch.as_tensor(template.triangles, device=device),
                           torch.as_tensor(template.uvs, dtype=torch.float32, device=device),
                           torch.as_tensor(texture, device=device), camera)
    rgb = out.rgb.clamp(0, 1).cpu().numpy()
    mask = (out.mask > 0.5).to(torch.float32).cpu().numpy()
    rng = np.random.default_rng(spec.seed + 1)
    gt_points = [sample_surface(p, template.triangles, spec.gt_points, rng) for p in positions]
    frames = FrameSequence((), None, spec.image_size, spec.image_size)
    scene = Scene(name="hanging-cloth", template=template, camera=camera, frames=frames, texture=None,
                  pinned=top_row, frame_dt=spec.frame_dt, gravity=gravity)
    return scene, rgb, mask, positions, gt_points


def write_hanging_cloth(folder: str | Path, spec: HangingClothSpec = HangingClothSpec(), device="cpu") -> Path:
    """Make the synthetic scene and write it as a native scene folder with ground truth (gt/*.npy)."""
    scene, rgb, mask, positions, gt_points = make_hanging_cloth(spec, device)
    folder = write_native_scene(folder, scene, rgb, mask, ground_truth=gt_points)
    atomic_save_npy(Path(folder) / "gt_vertices.npy", positions.astype(np.float32))
    return Path(folder)
