"""render_cloth: the renderer of the texture and shape phases (paper §3.2.1).

rasterize → interpolate (UV, camera depth, vertex normals, a constant-1 channel) → mip-mapped bilinear
texture → antialias (RGB and the coverage channel together, which gives the silhouette gradients of both).
render_cloth prepares the inputs and makes one backend call, rasterizer.render_cloth: the torch backend runs
its fused kernels (saft.render.torch.fused), nvdiffrast the four primitives (saft.render.reference).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from saft.render.backend import get_rasterizer
from saft.render.clip import camera_to_clip
from saft.render.output import RenderOutput
from saft.render.topology import topology
from saft.scene.camera import Camera


def _as_tensor(x, like: torch.Tensor, dtype=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=like.device, dtype=dtype or x.dtype)
    return torch.as_tensor(np.asarray(x), device=like.device, dtype=dtype)


MIP_MIN_TEXELS = 16  # the coarsest mip level kept has this many texels along its shorter side


def coarsest_mip_level(height: int, width: int) -> int:
    """render_cloth's default max_mip_level: the level whose shorter side is MIP_MIN_TEXELS texels (5 for a
    512² texture). A pixel would need a coarser level only if its footprint spanned more than a sixteenth of
    the texture, i.e. if the whole cloth covered fewer than about 16 × 16 pixels; R1's renders stay below
    level 1.1 even at a quarter of the resolution. nvdiffrast builds (and differentiates) every level up to
    the limit in each call: the four levels below 16 texels cost it eight launches per forward + backward."""
    return max(0, int(math.floor(math.log2(max(min(height, width), 1) / MIP_MIN_TEXELS))))


def render_cloth(vertices: torch.Tensor, triangles, uvs, texture: torch.Tensor, camera: Camera,
                 rasterizer=None, *, near: float | None = None, far: float | None = None,
                 max_mip_level: int | None = None, vertex_shading: torch.Tensor | None = None) -> RenderOutput:
    """Render textured cloth for the shape and texture phases.

    vertices: (B, V, 3) or (V, 3) world-frame positions (differentiable); triangles (T, 3) int;
    uvs (V, 2) OBJ convention (v up: (0, 0) is the bottom-left of the texture image); texture
    (Ht, Wt, 3) float, row 0 = top of the image (differentiable), used as it is (sRGB, no lighting);
    camera: saft Camera (already cropped/scaled as wanted; the output has its height and width).
    max_mip_level: the coarsest mip level the lookup may use; None: coarsest_mip_level of the texture.
    rasterizer: from get_rasterizer(); default 'auto' for the vertices' device.
    vertex_shading: optional (B|1, V, 3) per-vertex, per-channel factors (differentiable), interpolated
    perspective-correctly and multiplied into the texture colour before antialiasing (saft.render.shading).
    They are interpolated in the slot of the vertex normals, so the output then has no normals image.
    """
    if vertices.dim() == 2:
        vertices = vertices[None]
    R = rasterizer if rasterizer is not None else get_rasterizer("auto", vertices.device)
    tri = topology(triangles, vertices.device).tri  # int64 on the device, made once per triangle list
    uv = _as_tensor(uvs, vertices, vertices.dtype)
    tex = texture if isinstance(texture, torch.Tensor) else torch.as_tensor(np.asarray(texture))
    tex = tex.to(device=vertices.device)
    H, W = camera.height, camera.width

    if max_mip_level is None:
        max_mip_level = coarsest_mip_level(tex.shape[-3], tex.shape[-2])
    pos = camera_to_clip(vertices, camera, near=near, far=far)
    if vertex_shading is not None:
        vertex_shading = vertex_shading.to(vertices.dtype)
        if vertex_shading.dim() == 2:
            vertex_shading = vertex_shading[None]
        vertex_shading = vertex_shading.expand(vertices.shape[0], -1, -1)
    return R.render_cloth(vertices, pos, tri, uv, tex, H, W, max_mip_level, vertex_shading)
