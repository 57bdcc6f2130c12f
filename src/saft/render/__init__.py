"""saft.render — differentiable rasterization of the cloth (paper §3.2.1).

Two backends behind one interface: a vectorised PyTorch rasterizer (default on CPU, works on any device)
and nvdiffrast (chosen automatically on CUDA when the optional ``diffrp-nvdiffrast`` package imports).

Conventions
-----------
* Clip space is nvdiffrast's, with y_ndc = −1 at the TOP row (saft.render.clip), so every image-shaped
  output is (B, H, W, C) with row 0 = top, like all images in saft. Two-sided: back faces are visible.
* ``rast`` (B, H, W, 4) = (u, v, z/w, triangle_id + 1), 0 = empty; attributes interpolate as
  u·a0 + v·a1 + (1 − u − v)·a2 (perspective-correct).
* ``texture`` coordinates are nvdiffrast's: u → column, v → row from the top, texel centres at
  (i + 0.5)/size. render_cloth converts the OBJ UVs (v up) with v → 1 − v.

Public API
----------
camera_to_clip(vertices (…, V, 3), camera, *, crop=None, scale=None, near=None, far=None) -> (…, V, 4)
projection_matrix(camera, near, far) -> (4, 4) numpy;  effective_camera(camera, crop, scale) -> Camera
get_rasterizer(backend="auto"|"torch"|"nvdiffrast", device=None) -> rasterizer object with the four
    methods below (same signatures), and render_cloth(vertices, pos, tri, uv, tex, H, W, max_mip_level):
    the one backend call of render_cloth (torch: fused kernels, saft.render.torch.fused; nvdiffrast: the
    four primitives, saft.render.reference)
rasterize(pos (B, V, 4), tri (T, 3), resolution=(H, W), with_db=False) -> rast | (rast, rast_db)
interpolate(attr (B|1, V, C) | (V, C), rast, tri, rast_db=None, diff_attrs=None)
    -> out (B, H, W, C) | (out, out_da) when rast_db is given (out_da: (dA/dX, dA/dY) per listed attr)
texture(tex (B|1, Ht, Wt, C), uv (B, H, W, 2), uv_da=None, filter_mode="auto", boundary_mode="wrap",
    max_mip_level=None) -> (B, H, W, C); 'linear' or 'linear-mipmap-linear' (needs uv_da)
antialias(color (B, H, W, C), rast, pos, tri) -> (B, H, W, C), gradients to pos on every silhouette edge
    (mesh boundary, and fold edges between front- and back-facing triangles)
render_cloth(vertices (B, V, 3) | (V, 3), triangles (T, 3), uvs (V, 2), texture (Ht, Wt, 3), camera,
    rasterizer=None, *, near=None, far=None, max_mip_level=None, vertex_shading=None) -> RenderOutput(rgb,
    mask, depth, normals, rast, pos_clip); vertex_shading (B|1, V, 3): per-vertex colour factors
    (saft.render.shading.shading_ratio), interpolated in the normals' slot (no normals image then)
"""

from saft.render.backend import antialias, get_rasterizer, interpolate, rasterize, texture
from saft.render.clip import auto_near_far, camera_to_clip, effective_camera, projection_matrix
from saft.render.cloth import render_cloth
from saft.render.nvdiffrast_backend import NvdiffrastRasterizer, nvdiffrast_available
from saft.render.output import RenderOutput, vertex_normals
from saft.render.torch import TorchRasterizer

__all__ = [
    "NvdiffrastRasterizer",
    "RenderOutput",
    "TorchRasterizer",
    "antialias",
    "auto_near_far",
    "camera_to_clip",
    "effective_camera",
    "get_rasterizer",
    "interpolate",
    "nvdiffrast_available",
    "projection_matrix",
    "rasterize",
    "render_cloth",
    "texture",
    "vertex_normals",
]
