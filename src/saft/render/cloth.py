"""render_cloth: the renderer of the texture and shape phases (paper §3.2.1).

rasterize → interpolate (UV, camera depth, vertex normals, a constant-1 channel) → mip-mapped bilinear
texture → antialias (RGB and the coverage channel together, which gives the silhouette gradients of both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from saft.render.backend import get_rasterizer
from saft.render import torch_backend as tb
from saft.render.clip import camera_to_clip
from saft.render.torch_backend import TorchRasterizer
from saft.scene.camera import Camera


@dataclass
class RenderOutput:
    """rgb (B, H, W, 3): texture colours as they are (no lighting), black background, antialiased.
    mask (B, H, W): antialiased coverage in [0, 1] (differentiable, silhouette gradients).
    depth (B, H, W): metric camera z of the visible surface, 0 where empty (not antialiased).
    normals (B, H, W, 3): unit world-frame normals of the visible surface, interpolated from area-weighted
    vertex normals, oriented by the triangle winding (not flipped towards the camera); 0 where empty.
    rast (B, H, W, 4): the raw rasterizer output (u, v, z/w, triangle_id + 1) (detached on the torch
    backend, whose gradients flow through its own compact kernels).
    pos_clip (B, V, 4): the clip-space vertices used."""

    rgb: torch.Tensor
    mask: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor
    rast: torch.Tensor
    pos_clip: torch.Tensor


def vertex_normals(vertices: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) unit area-weighted vertex normals (right-hand rule on the triangle winding)."""
    B, T = vertices.shape[0], tri.shape[0]
    v = vertices.index_select(1, tri.T.reshape(-1)).reshape(B, 3, T, 3)  # index_select: index_add backward
    fn = torch.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], dim=-1)  # length = 2·area
    n = torch.zeros_like(vertices).index_add(1, tri.T.reshape(-1), fn.repeat(1, 3, 1))
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _as_tensor(x, like: torch.Tensor, dtype=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=like.device, dtype=dtype or x.dtype)
    return torch.as_tensor(np.asarray(x), device=like.device, dtype=dtype)


def render_cloth(vertices: torch.Tensor, triangles, uvs, texture: torch.Tensor, camera: Camera,
                 rasterizer=None, *, near: float | None = None, far: float | None = None,
                 max_mip_level: int | None = None) -> RenderOutput:
    """Render textured cloth for the shape and texture phases.

    vertices: (B, V, 3) or (V, 3) world-frame positions (differentiable); triangles (T, 3) int;
    uvs (V, 2) OBJ convention (v up: (0, 0) is the bottom-left of the texture image); texture
    (Ht, Wt, 3) float, row 0 = top of the image (differentiable), used as it is (sRGB, no lighting);
    camera: saft Camera (already cropped/scaled as wanted; the output has its height and width).
    rasterizer: from get_rasterizer(); default 'auto' for the vertices' device.
    """
    if vertices.dim() == 2:
        vertices = vertices[None]
    R = rasterizer if rasterizer is not None else get_rasterizer("auto", vertices.device)
    tri = _as_tensor(triangles, vertices, torch.int64)
    uv = _as_tensor(uvs, vertices, vertices.dtype)
    tex = texture if isinstance(texture, torch.Tensor) else torch.as_tensor(np.asarray(texture))
    tex = tex.to(device=vertices.device)
    tex3 = tex if tex.dim() == 3 else tex[0]  # the torch path takes (Ht, Wt, C) as it is (no select backward)
    if tex.dim() == 3:
        tex = tex[None]
    B, V, _ = vertices.shape
    H, W = camera.height, camera.width

    pos = camera_to_clip(vertices, camera, near=near, far=far)
    if isinstance(R, TorchRasterizer):
        return _render_cloth_torch(vertices, pos, tri, uv, tex3, H, W, max_mip_level)
    rast, rast_db = R.rasterize(pos, tri, (H, W), with_db=True)
    uv_tex = torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1)  # nvdiffrast texture: v → row from the top
    normals_v = vertex_normals(vertices, tri)
    attr = torch.cat([uv_tex[None].expand(B, V, 2), pos[..., 3:4], normals_v, torch.ones_like(pos[..., :1])],
                     dim=-1)
    pix, pix_da = R.interpolate(attr, rast, tri, rast_db=rast_db, diff_attrs=[0, 1])
    covered = rast[..., 3] > 0
    tex_rgb = R.texture(tex, pix[..., 0:2].contiguous(), pix_da, filter_mode="linear-mipmap-linear",
                        boundary_mode="clamp", max_mip_level=max_mip_level, mask=covered)
    cov = pix[..., 6:7]
    rgb = tex_rgb.to(cov.dtype) * cov
    aa = R.antialias(torch.cat([rgb, cov], dim=-1), rast, pos, tri)
    n = pix[..., 3:6]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return RenderOutput(rgb=aa[..., :3], mask=aa[..., 3], depth=pix[..., 2], normals=n, rast=rast,
                        pos_clip=pos)


def _render_cloth_torch(vertices, pos, tri, uv, tex, H, W, max_mip_level) -> RenderOutput:
    """The same pipeline on the covered pixels only: one per-triangle table of plane coefficients
    (tb.plane_table) evaluated per pixel with a hand-written backward, texture on the covered pixels, and
    dense images only at the end; identical in value to the primitive pipeline (tested)."""
    B, V, _ = vertices.shape
    T = tri.shape[0]
    n_pix = B * H * W
    pix, tid = tb.visibility(pos, tri, (H, W))
    with torch.no_grad():
        if B == 1:
            row_idx = tid
            rem = pix
        else:
            b = torch.div(pix, H * W, rounding_mode="floor")
            row_idx = b * T + tid
            rem = pix - b * (H * W)
        prow = torch.div(rem, W, rounding_mode="floor")
        pcol = rem - prow * W
        nx = (2.0 * pcol.to(pos.dtype) + 1.0) / W - 1.0
        ny = (2.0 * prow.to(pos.dtype) + 1.0) / H - 1.0
    uv_tex = torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1)
    normals_v = vertex_normals(vertices, tri)
    table = tb.plane_table(pos, tri, uv_tex, normals_v)
    uv_pix, depth_c, n, bw, zw, uv_da = tb.plane_interp(table, row_idx, nx, ny, H, W)
    rgb_c = tb.texture_fast(tex, uv_pix[0], uv_pix[1], uv_da, max_mip_level=max_mip_level)
    rgb_img = tb._ScatterPlanar.apply(rgb_c.to(pos.dtype), pix, n_pix).reshape(B, H, W, 3)
    cov_img = pos.new_zeros(n_pix).index_fill_(0, pix, 1.0).reshape(B, H, W)  # coverage, no gradient
    with torch.no_grad():
        tid_img = torch.full((n_pix,), -1, dtype=torch.long, device=pos.device).index_copy_(0, pix, tid)
        depth_img = torch.full((n_pix,), math.inf, dtype=pos.dtype, device=pos.device).index_copy_(0, pix, zw)
        rast = pos.new_zeros(n_pix, 4).index_copy_(
            0, pix, torch.stack([bw[0], bw[1], zw, (tid + 1).to(pos.dtype)], dim=-1))
    rgb, mask = tb.antialias_core((rgb_img, cov_img), tid_img.reshape(B, H, W), depth_img.reshape(B, H, W),
                                  pos, tri, split=True)
    depth = tb._scatter_rows(depth_c, pix, n_pix).reshape(B, H, W)
    n = n / (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().clamp_min(1e-12)  # (3, P): no dim-0 norm
    normals = tb._scatter_rows(n.T, pix, n_pix).reshape(B, H, W, 3)
    return RenderOutput(rgb=rgb, mask=mask, depth=depth, normals=normals, rast=rast.reshape(B, H, W, 4),
                        pos_clip=pos)
