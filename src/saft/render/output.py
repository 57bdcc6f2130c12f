"""What render_cloth returns, and the vertex normals every backend interpolates."""

from __future__ import annotations

from typing import Callable

import torch

from saft.render.topology import topology


class RenderOutput:
    """rgb (B, H, W, 3): texture colours as they are (no lighting), black background, antialiased.
    mask (B, H, W): antialiased coverage in [0, 1] (differentiable, silhouette gradients).
    depth (B, H, W): metric camera z of the visible surface, 0 where empty (not antialiased).
    normals (B, H, W, 3): unit world-frame normals of the visible surface, interpolated from area-weighted
    vertex normals, oriented by the triangle winding (not flipped towards the camera); 0 where empty.
    rast (B, H, W, 4): the raw rasterizer output (u, v, z/w, triangle_id + 1) (detached on the torch
    backend, whose gradients flow through its own compact kernels).
    pos_clip (B, V, 4): the clip-space vertices used.

    depth, normals and rast may be given as zero-argument functions: they are then made on first access.
    The shape phase reads no normals; on the torch backend, leaving the two dense images out saved 0-24 % of
    a 700 x 800 render's forward + backward in interleaved measurements (BENCHMARKS.md); on nvdiffrast the
    depth is its own interpolation, made only for the renders whose depth is read."""

    __slots__ = ("rgb", "mask", "pos_clip", "_depth", "_normals", "_rast")

    def __init__(self, rgb: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor | Callable[[], torch.Tensor],
                 normals: torch.Tensor | Callable[[], torch.Tensor], rast: torch.Tensor | Callable[[], torch.Tensor],
                 pos_clip: torch.Tensor):
        self.rgb, self.mask, self.pos_clip = rgb, mask, pos_clip
        self._depth, self._normals, self._rast = depth, normals, rast

    @property
    def depth(self) -> torch.Tensor:
        if callable(self._depth):
            self._depth = self._depth()
        return self._depth

    @property
    def normals(self) -> torch.Tensor:
        if callable(self._normals):
            self._normals = self._normals()
        return self._normals

    @property
    def rast(self) -> torch.Tensor:
        if callable(self._rast):
            self._rast = self._rast()
        return self._rast


def vertex_normals(vertices: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) unit area-weighted vertex normals (right-hand rule on the triangle winding)."""
    B, T = vertices.shape[0], tri.shape[0]
    tft = topology(tri).tri_flat_t  # tri.T.reshape(-1), made once per triangle list
    # index_select: an index_add backward; unbind: one stack (three selects would zero-fill and copy each)
    v0, v1, v2 = vertices.index_select(1, tft).reshape(B, 3, T, 3).unbind(1)
    fn = torch.cross(v1 - v0, v2 - v0, dim=-1)  # length = 2·area
    n = torch.zeros_like(vertices).index_add(1, tft, fn.repeat(1, 3, 1))
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def no_normals() -> torch.Tensor:
    """RenderOutput.normals of a render with vertex_shading: the shading took the normals' slot."""
    raise ValueError("this render interpolated vertex_shading in the normals' slot: it has no normals image")
