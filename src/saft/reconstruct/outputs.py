"""Writing the shape phases' results into the result folder (layout: saft.result), atomically."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from saft.io_utils import atomic_save_npy, atomic_write_json, atomic_write_text, write_image
from saft.reconstruct.force_field import affine_basis, total_accelerations
from saft.result import MESH_MTL, mesh_path, mtl_text
from saft.scene import Scene, write_obj
from saft.scene.camera import Camera

RENDER_BATCH = 8
# The side-by-side renders' PNG encoding was most of this phase (R1: 0.12 s per 700 x 2400 image at zlib's
# default level 6, 10.1 s of outputs on the H100 machine): level 1 takes 0.063 s for files 13 % larger, and a
# thread pool spreads them over the cores (zlib releases the GIL).
RENDER_PNG_LEVEL = 1


def side_by_side(rendered: np.ndarray, target: np.ndarray) -> np.ndarray:
    """rendered | target | |difference| (difference amplified ×4 for visibility), H × 3W × 3."""
    diff = np.clip(np.abs(rendered - target) * 4.0, 0.0, 1.0)
    return np.concatenate([rendered, target, diff], axis=1)


def write_shape_outputs(out_dir: Path, scene: Scene, camera: Camera, positions: np.ndarray, texture: torch.Tensor,
                        raw_params: dict, params: dict, ctx) -> None:
    out_dir = Path(out_dir)
    tex = texture.detach().cpu().numpy()
    write_image(out_dir / "texture.png", tex)
    atomic_write_text(out_dir / "meshes" / MESH_MTL, mtl_text())
    for i, verts in enumerate(positions):
        write_obj(mesh_path(out_dir, i), scene.template, verts, comment=f"saft frame {i} (world frame, metres)",
                  mtllib=MESH_MTL)
    atomic_write_json(out_dir / "params.json", params)
    accel = raw_params["vertex_accel"]
    forces = total_accelerations(accel, raw_params.get("field_accel"),
                                 affine_basis(torch.as_tensor(scene.template.vertices, dtype=accel.dtype)))
    atomic_save_npy(out_dir / "forces.npy", forces.numpy().astype(np.float32))
    atomic_write_json(out_dir / "scene.json", {
        "name": scene.name, "source": str(scene.source) if scene.source else None,
        "num_frames": int(len(positions)), "frame_dt": scene.frame_dt,
        "gravity": [float(g) for g in scene.gravity_or_default()], "gravity_given": scene.gravity is not None,
        "camera": camera.to_json(), "full_camera": scene.camera.to_json(),
        "crop": scene.crop.to_json() if scene.crop else None,
        "ground_truth_dir": str(scene.ground_truth_dir) if scene.ground_truth_dir else None,
        "ground_truth_frame": scene.ground_truth_frame,
    })
    with torch.no_grad(), ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1))) as pool:
        pos = torch.as_tensor(positions, dtype=torch.float32, device=ctx.device)
        tex_t = texture.to(ctx.device)
        writes = []
        for start in range(0, len(pos), RENDER_BATCH):
            out = ctx.render(pos[start:start + RENDER_BATCH], tex_t)
            rgb = out.rgb.clamp(0, 1).cpu().numpy()
            target = ctx.target_rgb[start:start + rgb.shape[0]].cpu().numpy()
            for j in range(rgb.shape[0]):
                writes.append(pool.submit(write_image, out_dir / "renders" / f"frame_{start + j:03d}.png",
                                          side_by_side(rgb[j], target[j]), RENDER_PNG_LEVEL))
        for w in writes:
            w.result()  # raises what a write raised
