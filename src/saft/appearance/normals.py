"""A small, smooth per-frame correction of the shading normals, learnt in phase 3 (appearance.normal_grid).

On saft's own motion the meshes are off by about a centimetre and their normals are tilted by 5-20°, so
the highlights of a glossy fabric fall where the meshes' normals do not predict them, and the fit answers
by blurring the material (rough, non-metal). This module lets the fit tilt the shading normals a little:

    n_f(x) = normalise(n_geo,f(x) + a_f(x) t_f(x) + b_f(x) s_f(x)),

with (t, s) an orthonormal tangent frame that follows the texture's u direction, and (a, b) a bilinear
field over the UV square on a g × g grid whose values are keyframes in time, linearly interpolated between
them (so a frame seen once still moves with its neighbours, and the few parameters cannot paint a texture
or a highlight out of nothing). Frame 0 is the template, which the user gave: its correction is zero.
Only the shading normals change (Mitsuba's ``vertex_normals``: gradients of the shading need no
reparameterisation of the visibility); the positions stay saft's.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from saft.scene.mesh import vertex_normals


def uv_hat_basis(uvs: np.ndarray, grid: int) -> np.ndarray:
    """(V, grid²) bilinear hat functions of the vertices' UVs on a grid × grid lattice over [0, 1]²
    (partition of unity; grid = 1: one constant)."""
    uv = np.clip(np.asarray(uvs, dtype=np.float64).reshape(-1, 2), 0.0, 1.0)
    if grid == 1:
        return np.ones((uv.shape[0], 1))
    x = uv * (grid - 1)
    i0 = np.minimum(np.floor(x).astype(int), grid - 2)
    w1 = x - i0
    out = np.zeros((uv.shape[0], grid, grid))
    rows = np.arange(uv.shape[0])
    for di in (0, 1):
        for dj in (0, 1):
            wu = w1[:, 0] if di else 1.0 - w1[:, 0]
            wv = w1[:, 1] if dj else 1.0 - w1[:, 1]
            np.add.at(out, (rows, i0[:, 0] + di, i0[:, 1] + dj), wu * wv)
    return out.reshape(uv.shape[0], grid * grid)


def tangent_frames(vertices: np.ndarray, triangles: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per frame the unit vertex normals n (F, V, 3) and a tangent frame (t, s): t along ∂P/∂u projected
    on the tangent plane, s = n × t."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    uv = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)
    d1, d2 = uv[tri[:, 1]] - uv[tri[:, 0]], uv[tri[:, 2]] - uv[tri[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = np.where(np.abs(det) < 1e-12, 1e-12, det)
    ns, ts, ss = [], [], []
    for frame in v:
        n = vertex_normals(frame, tri)
        e1, e2 = frame[tri[:, 1]] - frame[tri[:, 0]], frame[tri[:, 2]] - frame[tri[:, 0]]
        dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
        t = np.zeros_like(frame)
        for k in range(3):
            np.add.at(t, tri[:, k], dpdu)
        t = t - (t * n).sum(1, keepdims=True) * n
        bad = np.linalg.norm(t, axis=1) < 1e-12
        if bad.any():   # any direction in the tangent plane
            alt = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
            alt = alt - (alt * n).sum(1, keepdims=True) * n
            t[bad] = alt[bad]
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        ns.append(n)
        ts.append(t)
        ss.append(np.cross(n, t))
    return np.stack(ns), np.stack(ts), np.stack(ss)


class NormalCorrection(nn.Module):
    """Per-frame shading normals n_f = normalise(n + a t + b s), (a, b) = basis · C(f) (module docstring).

    vertices (F, V, 3), triangles, uvs (V, 2); grid: the UV lattice's side; keys: keyframes in time (0 or
    >= F: one per frame), evenly spaced over frames 0 … F-1 and linearly interpolated; the key at frame 0
    is held at zero (the template is the user's), so the correction grows from there.
    """

    def __init__(self, vertices, triangles, uvs, grid: int = 3, keys: int = 8):
        super().__init__()
        n, t, s = tangent_frames(vertices, triangles, uvs)
        frames = n.shape[0]
        self.register_buffer("normals", torch.as_tensor(n, dtype=torch.float32))
        self.register_buffer("tangents", torch.as_tensor(np.stack([t, s], axis=2), dtype=torch.float32))  # F,V,2,3
        self.register_buffer("basis", torch.as_tensor(uv_hat_basis(uvs, grid), dtype=torch.float32))     # V, G
        keys = frames if keys <= 0 or keys >= frames else max(int(keys), 2)
        pos = np.linspace(0, keys - 1, frames) if frames > 1 else np.zeros(1)
        lo = np.minimum(np.floor(pos).astype(int), max(keys - 2, 0))
        self.lo, self.w = lo.tolist(), (pos - lo).tolist()
        self.coeffs = nn.Parameter(torch.zeros(max(keys - 1, 1), grid * grid, 2))   # keys 1 … K-1

    def offsets(self, frame: int) -> torch.Tensor:
        """(G, 2) coefficients of this frame (key 0, at frame 0, is zero)."""
        keys = torch.cat([torch.zeros_like(self.coeffs[:1]), self.coeffs])
        lo, w = self.lo[frame], self.w[frame]
        c = keys[lo] * (1.0 - w)
        if lo + 1 < keys.shape[0]:
            c = c + keys[lo + 1] * w
        return c

    def forward(self, frame: int) -> torch.Tensor:
        """(V, 3) unit shading normals of this frame."""
        ab = self.basis @ self.offsets(frame)                                    # V, 2
        n = self.normals[frame] + (ab[:, :, None] * self.tangents[frame]).sum(1)
        return n / n.norm(dim=1, keepdim=True).clamp_min(1e-8)

    def penalty(self) -> torch.Tensor:
        """Mean squared tangent offset per coefficient (the prior towards the meshes' own normals)."""
        return (self.coeffs ** 2).mean()

    @torch.no_grad()
    def tilt_degrees(self) -> np.ndarray:
        """Per frame the mean angle (degrees) between the corrected and the meshes' normals."""
        out = []
        for f in range(self.normals.shape[0]):
            cos = (self(f) * self.normals[f]).sum(1).clamp(-1.0, 1.0)
            out.append(float(torch.rad2deg(torch.arccos(cos)).mean()))
        return np.asarray(out)
