"""Small scenes shared by the render tests (imported by file name: no __init__.py in test folders)."""

from __future__ import annotations

import numpy as np
import torch

from saft.scene.camera import Camera


def pinhole(width: int, height: int, f: float) -> Camera:
    """Camera at the origin looking down +z (identity world_to_camera), principal point at the centre."""
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return Camera(K, np.eye(4), width, height)


def grid(n: int, x0: float, x1: float, y0: float, y1: float, z: float):
    """n×n-vertex grid (vertices (n², 3), triangles, uvs with v up = −y)."""
    xs, ys = np.linspace(x0, x1, n), np.linspace(y0, y1, n)
    X, Y = np.meshgrid(xs, ys)
    verts = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], axis=1)
    uvs = np.stack([(X.ravel() - x0) / (x1 - x0), 1 - (Y.ravel() - y0) / (y1 - y0)], axis=1)
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            tris += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return verts, np.array(tris, dtype=np.int64), uvs


def smooth_texture(size: int = 16, dtype=torch.float64) -> torch.Tensor:
    u = torch.linspace(0, 1, size, dtype=dtype)
    U, V = torch.meshgrid(u, u, indexing="xy")
    return torch.stack([0.2 + 0.6 * U, 0.3 + 0.5 * V, 0.5 + 0.3 * torch.sin(3 * U + 2 * V)], dim=-1)


def box_down(img: torch.Tensor, s: int) -> torch.Tensor:
    """(B, H·s, W·s, C) → (B, H, W, C) mean over s×s blocks."""
    B, H, W, C = img.shape
    return img.reshape(B, H // s, s, W // s, s, C).mean(dim=(2, 4))


def folded_sheet():
    """A sheet folded back on itself: the left half at z = 1, the right half folded under it along the
    vertical line x = 0.05, going back to the left at z ≈ 1.1. Seen from the origin the fold edge is a
    silhouette between front- and back-facing triangles; the mesh boundary there is elsewhere."""
    n = 4
    ys = np.linspace(-0.12, 0.12, n)
    cols_front = np.linspace(-0.12, 0.05, n)  # x at z = 1, the last column is the fold
    cols_back = np.linspace(0.05, -0.08, n)[1:]  # folded part, behind
    zs_back = np.linspace(1.0, 1.1, n)[1:]
    verts, uvs = [], []
    ncol = 2 * n - 1
    for i, y in enumerate(ys):
        for j in range(ncol):
            if j < n:
                verts.append([cols_front[j], y, 1.0])
            else:
                verts.append([cols_back[j - n], y, zs_back[j - n]])
            uvs.append([j / (ncol - 1), 1 - i / (n - 1)])
    tris = []
    for i in range(n - 1):
        for j in range(ncol - 1):
            a = i * ncol + j
            tris += [[a, a + 1, a + ncol + 1], [a, a + ncol + 1, a + ncol]]
    fold_vertices = [i * ncol + (n - 1) for i in range(n)]
    return np.array(verts), np.array(tris, dtype=np.int64), np.array(uvs), fold_vertices
