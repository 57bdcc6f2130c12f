"""render_cloth as four primitive calls on any rasterizer object: the nvdiffrast backend's render_cloth,
and the reference the torch backend's fused path (saft.render.torch.fused) is tested against."""

from __future__ import annotations

import torch

from saft.render.output import RenderOutput, no_normals, vertex_normals
from saft.render.topology import TensorCache


def render_cloth_primitives(R, vertices: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor, uv: torch.Tensor,
                            tex: torch.Tensor, H: int, W: int, max_mip_level: int | None,
                            shading: torch.Tensor | None = None) -> RenderOutput:
    """rasterize → interpolate (UV[, shading]) → mip-mapped texture → antialias with R's primitives.
    vertices (B, V, 3), pos (B, V, 4) clip space, tri (T, 3) int64, uv (V, 2) OBJ convention,
    tex (Ht, Wt, C) or (B|1, Ht, Wt, C); shading: None or (B, V, 3) per-vertex factors, interpolated and
    multiplied into the colour before antialias (normals are then not available).

    Written for few launches per forward + backward on a GPU, where each op of saft's around nvdiffrast's
    kernels costs a launch (`bench_render_ops.py --path primitives`): the UVs in the texture's convention
    are made once per UV tensor and interpolated as one (1, V, 2) attribute broadcast over the batch (no
    gradient to them: the interpolation's backward goes to the barycentrics only); the coverage is the
    rasterizer's triangle id + 1 clamped at 1 (exactly 1 or 0); colour and coverage leave antialias as one
    split (its backward is one concatenation, where slices cost two zero-fills, two copies and an add). The
    depth and normals images are made on first access, each by its own interpolation: the texture phase
    reads neither, the shape phase reads the depth (detached, for the tracks' occlusion test) and never the
    normals."""
    if tex.dim() == 3:
        tex = tex[None]
    rast, rast_db = R.rasterize(pos, tri, (H, W), with_db=True)
    attr = texture_uv(uv)[None]
    if shading is not None:
        attr = torch.cat([attr.expand(shading.shape[0], -1, -1), shading], dim=-1)
    pix, pix_da = R.interpolate(attr, rast, tri, rast_db=rast_db, diff_attrs=[0, 1])
    cov = rast.detach()[..., 3:4].clamp(max=1.0)
    tex_rgb = R.texture(tex, pix if shading is None else pix[..., 0:2].contiguous(), pix_da,
                        filter_mode="linear-mipmap-linear", boundary_mode="clamp", max_mip_level=max_mip_level)
    rgb = tex_rgb.to(cov.dtype) * (cov if shading is None else pix[..., 2:5] * cov)
    aa_rgb, aa_mask = R.antialias(torch.cat([rgb, cov], dim=-1), rast, pos, tri).split([3, 1], dim=-1)

    def depth():
        return R.interpolate(pos[..., 3:4], rast, tri)[..., 0]

    if shading is None:
        def normals():
            n = R.interpolate(vertex_normals(vertices, tri), rast, tri)
            return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    else:
        normals = no_normals
    return RenderOutput(rgb=aa_rgb, mask=aa_mask.squeeze(-1), depth=depth, normals=normals, rast=rast,
                        pos_clip=pos)


_UV = TensorCache()  # uv tensor → its texture-convention copy


def texture_uv(uv: torch.Tensor) -> torch.Tensor:
    """(V, 2) UVs in the texture lookup's convention (v → row from the top: (u, 1 − v)), made once per UV
    tensor (found by identity: saft.render.topology.TensorCache). UVs that need a gradient are converted on
    every call."""
    if uv.requires_grad:
        return torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1)
    out = _UV.get(uv)
    return out if out is not None else _UV.put(uv, torch.stack([uv[:, 0], 1.0 - uv[:, 1]], dim=-1))
