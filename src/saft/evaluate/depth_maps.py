"""Depth maps for the depth error δ when the ground truth is a point cloud per frame (e.g. R1's sensor clouds).

The paper reports δ = mean |D_rendered − D_gt| over the pixels where both depth maps have a value. Where a
scene brings point clouds rather than depth images, the ground-truth depth map is the clouds' points
projected into the result's working camera (nearest point per pixel), and the rendered one is the
reconstructed mesh rasterized by the same camera. The pixel grid is the working camera resized so that
there are about two cloud points per pixel where the cloth is, so that the ground-truth map is dense
without being blurred; both maps share it.
"""

from __future__ import annotations

import numpy as np
import torch

from saft.render import render_cloth
from saft.scene.camera import Camera

POINTS_PER_PIXEL = 2.0


def depth_camera(camera: Camera, points: np.ndarray) -> Camera:
    """`camera` resized (never enlarged) so that the projected cloud has about POINTS_PER_PIXEL points per pixel."""
    uv, z = camera.project(points)
    uv = uv[z > 0]
    if len(uv) < 4:
        return camera
    area = float(np.prod(np.ptp(uv, axis=0)))          # bounding box of the cloud, in pixels
    if area <= 0:
        return camera
    factor = min(1.0, float(np.sqrt(len(uv) / (POINTS_PER_PIXEL * area))))
    return camera.scaled(factor) if factor < 1.0 else camera


def point_cloud_depth(points: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) camera-z of the nearest point of the world-frame cloud in each pixel, NaN where none."""
    uv, z = camera.project(points)
    col, row = np.floor(uv[:, 0] + 0.5).astype(np.int64), np.floor(uv[:, 1] + 0.5).astype(np.int64)
    keep = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    depth = np.full(camera.height * camera.width, np.inf)
    np.minimum.at(depth, row[keep] * camera.width + col[keep], z[keep])
    depth[~np.isfinite(depth)] = np.nan
    return depth.reshape(camera.height, camera.width)


def mesh_depth(vertices: np.ndarray, triangles: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) camera-z of the visible surface of the world-frame mesh, NaN where empty (saft.render, CPU)."""
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float32)
    uvs = torch.zeros(len(v), 2)
    with torch.no_grad():
        out = render_cloth(v, np.asarray(triangles), uvs, torch.ones(1, 1, 3), camera)
    depth = out.depth[0].numpy().astype(np.float64)
    depth[~(depth > 0)] = np.nan
    return depth


def depth_pairs(meshes: list[tuple[np.ndarray, np.ndarray]], gt_frames: list[np.ndarray],
                camera: Camera) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rendered, ground truth) depth maps per frame on one pixel grid (chosen from the first cloud); a vertex
    array given for several frames (a static mesh) is rendered once."""
    grid = depth_camera(camera, gt_frames[0])
    rendered: dict[int, np.ndarray] = {}
    pairs = []
    for (vertices, triangles), gt in zip(meshes, gt_frames):
        if id(vertices) not in rendered:
            rendered[id(vertices)] = mesh_depth(vertices, triangles, grid)
        pairs.append((rendered[id(vertices)], point_cloud_depth(gt, grid)))
    return pairs
