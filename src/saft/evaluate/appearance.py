"""Appearance metrics against known material maps and environment maps (issue 28).

How a scene folder stores appearance ground truth (``appearance_gt/``, beside scene.json)::

    appearance_gt/base_color.png     sRGB-encoded base colour (the principled BSDF's, linear after decoding)
    appearance_gt/roughness.png      principled roughness, stored linearly (as saft's material/ maps)
    appearance_gt/metallic.png       metallic, stored linearly
    appearance_gt/envmap_video.exr   linear lat-long radiance that lit the video (Mitsuba's convention)
    appearance_gt/envmap_unseen.exr  a light never shown, for relighting
    appearance_gt/appearance_gt.json {"max_depth": path length the video was rendered with, ...}
    gt_vertices.npy                  (F, V, 3) true geometry, world frame (for the relit novel views)
    gt_mesh.obj                      optional: the true geometry's own mesh (its triangles and UVs), where
                                     it is not the template's (a finer mesh, another simulator's)

Metrics (``appearance_metrics``), over the texels the template's UV layout covers:

* ``diffuse_psnr_db``: PSNR (peak 1) of the linear base colour after the best per-channel scale (least
  squares; albedo × light is ambiguous); ``diffuse_scale`` that scale;
* ``roughness_mae``, ``metallic_mae``: mean absolute errors (estimates resampled to the GT's size);
* ``relit_video_psnr_db``, ``relit_unseen_psnr_db``: masked sRGB PSNR of novel views (the camera turned by
  ±30° about the cloth, first / middle / last frame), rendered with the TRUE geometry under the TRUE
  environment map (video light, unseen light), the estimated maps with the diffuse map's per-channel
  scale applied, against the same views rendered with the true maps. Both at ``spp`` samples, same seeds.

``texture_baseline(texture_srgb)``: the phase-1 texture as the diffuse map with roughness 1 and metallic 0
(no phase 3 at all), the baseline every phase-3 result must beat.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as Fnn

from saft.appearance.detail import texel_triangles
from saft.appearance.fit import read_exr, write_exr
from saft.appearance.params import linear_to_srgb, srgb_to_linear
from saft.appearance.renderer import ClothRenderer
from saft.errors import SaftInputError
from saft.io_utils import atomic_write_json, read_image, write_image
from saft.render import render_cloth
from saft.scene.camera import Camera, orbit_camera
from saft.scene.mesh import QuadMesh, read_obj

APPEARANCE_GT_DIR = "appearance_gt"
GT_MESH_FILE = "gt_mesh.obj"
NOVEL_ANGLES = (-30.0, 30.0)
METRIC_NAMES = ("diffuse_psnr_db", "roughness_mae", "metallic_mae", "relit_video_psnr_db", "relit_unseen_psnr_db")
HIGHER_IS_BETTER = {"diffuse_psnr_db": True, "roughness_mae": False, "metallic_mae": False,
                    "relit_video_psnr_db": True, "relit_unseen_psnr_db": True}


@dataclass
class AppearanceGroundTruth:
    base_color: np.ndarray      # (S, S, 3) linear
    roughness: np.ndarray       # (S, S)
    metallic: np.ndarray        # (S, S)
    env_video: np.ndarray       # (He, We, 3) linear
    env_unseen: np.ndarray      # (He, We, 3) linear
    info: dict


def write_appearance_ground_truth(folder, base_color, roughness, metallic, env_video, env_unseen,
                                  info: dict) -> Path:
    """Write appearance_gt/ (see the module docstring)."""
    folder = Path(folder)
    write_image(folder / "base_color.png", linear_to_srgb(torch.as_tensor(base_color)).numpy())
    write_image(folder / "roughness.png", roughness)
    write_image(folder / "metallic.png", metallic)
    write_exr(folder / "envmap_video.exr", env_video)
    write_exr(folder / "envmap_unseen.exr", env_unseen)
    atomic_write_json(folder / "appearance_gt.json", info)
    return folder


def read_appearance_ground_truth(scene_folder) -> AppearanceGroundTruth | None:
    """The appearance ground truth of a scene folder, or None when it has none."""
    folder = Path(scene_folder) / APPEARANCE_GT_DIR
    if not (folder / "appearance_gt.json").is_file():
        return None
    try:
        info = json.loads((folder / "appearance_gt.json").read_text())
    except ValueError as exc:
        raise SaftInputError(folder / "appearance_gt.json", f"not JSON ({exc})") from None
    return AppearanceGroundTruth(srgb_to_linear(read_image(folder / "base_color.png")[..., :3]),
                                 read_image(folder / "roughness.png")[..., 0], read_image(folder / "metallic.png")[..., 0],
                                 read_exr(folder / "envmap_video.exr")[..., :3],
                                 read_exr(folder / "envmap_unseen.exr")[..., :3], info)


def true_geometry(scene_folder, template: QuadMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vertices (F, V, 3) float64, triangles, uvs) of the scene's true geometry, the relit views' (module
    docstring): gt_vertices.npy on gt_mesh.obj's topology where the scene has one, else on the template's;
    None without gt_vertices.npy."""
    folder = Path(scene_folder)
    if not (folder / "gt_vertices.npy").is_file():
        return None
    verts = np.load(folder / "gt_vertices.npy").astype(np.float64)
    mesh = read_obj(folder / GT_MESH_FILE) if (folder / GT_MESH_FILE).is_file() else template
    if verts.shape[1] != mesh.num_vertices:
        raise SaftInputError(folder / "gt_vertices.npy", f"{verts.shape[1]} vertices per frame, but its mesh has "
                             f"{mesh.num_vertices}")
    return verts, mesh.triangles, mesh.uvs


def texture_baseline(texture_srgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(diffuse linear, roughness 1, metallic 0): the phase-1 texture used as the diffuse map."""
    tex = np.asarray(texture_srgb, dtype=np.float32)[..., :3]
    size = tex.shape[:2]
    return srgb_to_linear(tex), np.ones(size, np.float32), np.zeros(size, np.float32)


def resize_map(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A map (H, W) or (H, W, C) resampled to `shape` (area when shrinking, bilinear when growing)."""
    a = np.asarray(a, dtype=np.float32)
    if a.shape[:2] == tuple(shape):
        return a
    t = torch.as_tensor(a.reshape(*a.shape[:2], -1)).permute(2, 0, 1)[None]
    mode = "area" if a.shape[0] > shape[0] else "bilinear"
    t = Fnn.interpolate(t, size=shape, mode=mode, **({} if mode == "area" else {"align_corners": False}))
    return t[0].permute(1, 2, 0).numpy().reshape(*shape, *a.shape[2:])


def uv_coverage(triangles, uvs, size: int) -> np.ndarray:
    """(size, size) bool: texels whose centre lies in a UV triangle (row 0 = top, v = 1)."""
    return texel_triangles(triangles, uvs, size)[0] >= 0


def per_channel_scale(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) s minimising Σ_mask (s·estimate − truth)² per channel."""
    e, t = estimate[mask], truth[mask]
    return ((e * t).sum(0) / np.maximum((e * e).sum(0), 1e-12)).astype(np.float32)


def psnr(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def map_metrics(diffuse, roughness, metallic, gt: AppearanceGroundTruth, coverage: np.ndarray) -> dict:
    """The three map metrics (module docstring) over `coverage` (GT-sized bool)."""
    shape = gt.roughness.shape
    d = resize_map(diffuse, shape)
    scale = per_channel_scale(d, gt.base_color, coverage)
    mse = float((((d * scale - gt.base_color) ** 2)[coverage]).mean())
    return {"diffuse_psnr_db": psnr(mse), "diffuse_scale": [float(s) for s in scale],
            "roughness_mae": float(np.abs(resize_map(roughness, shape) - gt.roughness)[coverage].mean()),
            "metallic_mae": float(np.abs(resize_map(metallic, shape) - gt.metallic)[coverage].mean())}


def novel_cameras(camera: Camera, vertices: np.ndarray) -> list[tuple[int, Camera]]:
    """(frame, camera) of the relit novel views: ±30° about the cloth's centre, first/middle/last frame."""
    frames = sorted({0, len(vertices) // 2, len(vertices) - 1})
    return [(f, orbit_camera(camera, vertices[f].mean(axis=0), a)) for f in frames for a in NOVEL_ANGLES]


def relit_metrics(diffuse, roughness, metallic, gt: AppearanceGroundTruth, vertices, triangles, uvs,
                  camera: Camera, spp: int = 64, device="cpu") -> dict:
    """PSNR (sRGB, inside the cloth) of the novel views under the video light and the unseen light."""
    depth = int(gt.info.get("max_depth", 3))
    out = {}
    for light, env in (("video", gt.env_video), ("unseen", gt.env_unseen)):
        se, n = 0.0, 0.0
        for k, (f, cam) in enumerate(novel_cameras(camera, vertices)):
            r_true = ClothRenderer(triangles, uvs, cam, device=device, max_depth=depth, map_shape=gt.roughness.shape,
                                   env_shape=env.shape[:2])
            r_true.set_vertices(vertices[f])
            truth = r_true.render_numpy(gt.base_color, gt.roughness, gt.metallic, env, spp=spp, seed=k)
            est = r_true.render_numpy(diffuse, roughness, metallic, env, spp=spp, seed=k)
            with torch.no_grad():
                mask = render_cloth(torch.tensor(vertices[f][None], dtype=torch.float32), torch.as_tensor(triangles),
                                    torch.as_tensor(uvs, dtype=torch.float32), torch.zeros(4, 4, 3), cam).mask
            m = (mask.reshape(cam.height, cam.width) > 0.5).numpy()
            diff = (linear_to_srgb(torch.as_tensor(est)) - linear_to_srgb(torch.as_tensor(truth))).numpy()
            se += float((diff[m] ** 2).sum())
            n += 3.0 * m.sum()
        out[f"relit_{light}_psnr_db"] = psnr(se / max(n, 1.0))
    return out


def appearance_metrics(diffuse, roughness, metallic, gt: AppearanceGroundTruth, vertices, triangles, uvs,
                       camera: Camera, spp: int = 64, device="cpu") -> dict:
    """Every metric of the module docstring for one set of estimated maps (numpy, row 0 = top)."""
    coverage = uv_coverage(triangles, uvs, gt.roughness.shape[0])
    maps = map_metrics(diffuse, roughness, metallic, gt, coverage)
    scaled = np.clip(np.asarray(diffuse, np.float32) * np.asarray(maps["diffuse_scale"], np.float32), 0.0, 1.0)
    rough = np.asarray(roughness, np.float32)
    metal = np.asarray(metallic, np.float32)
    return {**maps, **relit_metrics(scaled, rough, metal, gt, np.asarray(vertices), triangles, uvs, camera, spp,
                                    device)}


def beats(a: dict, b: dict) -> dict[str, bool]:
    """Per metric (those both give): whether result a is better than result b."""
    return {k: (a[k] > b[k]) if HIGHER_IS_BETTER[k] else (a[k] < b[k]) for k in METRIC_NAMES if k in a and k in b}
