"""render_cloth as four primitive calls on any rasterizer object: the nvdiffrast backend's render_cloth,
and the reference the torch backend's fused path (saft.render.torch.fused) is tested against."""

from __future__ import annotations

import torch

from saft.render.output import RenderOutput, no_normals, vertex_normals


def render_cloth_primitives(R, vertices: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor, uv: torch.Tensor,
                            tex: torch.Tensor, H: int, W: int, max_mip_level: int | None,
                            shading: torch.Tensor | None = None) -> RenderOutput:
    """rasterize → interpolate (UV, camera depth[, shading]) → mip-mapped texture → antialias with R's
    primitives. vertices (B, V, 3), pos (B, V, 4) clip space, tri (T, 3) int64, uv (V, 2) OBJ convention,
    tex (Ht, Wt, C) or (B|1, Ht, Wt, C); shading: None or (B, V, 3) per-vertex factors, interpolated and
    multiplied into the colour before antialias (normals are then not available).

    The normals image is made on first access (a second interpolate, differentiable like the colours): the
    shape and texture phases never read it, and computing it in every render cost about 40 of the ~120 ops
    (= CUDA launches) that saft adds around nvdiffrast's kernels per forward + backward
    (`bench_render_ops.py --path primitives`). The coverage channel is the rasterizer's triangle id > 0,
    which an interpolated constant 1 equals up to rounding."""
    if tex.dim() == 3:
        tex = tex[None]
    B, V, _ = vertices.shape
    rast, rast_db = R.rasterize(pos, tri, (H, W), with_db=True)
    uv_tex = torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1)  # nvdiffrast texture: v → row from the top
    attrs = [uv_tex[None].expand(B, V, 2), pos[..., 3:4]]
    if shading is not None:
        attrs.append(shading)
    pix, pix_da = R.interpolate(torch.cat(attrs, dim=-1), rast, tri, rast_db=rast_db, diff_attrs=[0, 1])
    covered = rast[..., 3] > 0
    tex_rgb = R.texture(tex, pix[..., 0:2].contiguous(), pix_da, filter_mode="linear-mipmap-linear",
                        boundary_mode="clamp", max_mip_level=max_mip_level, mask=covered)
    cov = covered[..., None].to(pos.dtype)
    rgb = tex_rgb.to(cov.dtype) * (cov if shading is None else pix[..., 3:6] * cov)
    aa = R.antialias(torch.cat([rgb, cov], dim=-1), rast, pos, tri)
    if shading is None:
        def normals():
            n = R.interpolate(vertex_normals(vertices, tri), rast, tri)
            return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    else:
        normals = no_normals
    return RenderOutput(rgb=aa[..., :3], mask=aa[..., 3], depth=pix[..., 2], normals=normals, rast=rast,
                        pos_clip=pos)
