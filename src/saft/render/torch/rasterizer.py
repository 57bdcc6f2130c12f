"""TorchRasterizer: the torch backend object that get_rasterizer returns."""

from __future__ import annotations

import torch

from saft.render.output import RenderOutput
from saft.render.torch.antialias import antialias
from saft.render.torch.fused import render_cloth_fused
from saft.render.torch.interpolate import interpolate
from saft.render.torch.raster import rasterize
from saft.render.torch.texture import texture


class TorchRasterizer:
    """The PyTorch backend (any device). Stateless."""

    name = "torch"

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)

    rasterize = staticmethod(rasterize)
    interpolate = staticmethod(interpolate)
    texture = staticmethod(texture)
    antialias = staticmethod(antialias)

    @staticmethod
    def render_cloth(vertices: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor, uv: torch.Tensor,
                     tex: torch.Tensor, H: int, W: int, max_mip_level: int | None,
                     shading: torch.Tensor | None = None) -> RenderOutput:
        """saft.render.render_cloth's backend call (arguments prepared there): the fused kernels."""
        tex3 = tex if tex.dim() == 3 else tex[0]  # the fused path takes (Ht, Wt, C) as it is (no select backward)
        return render_cloth_fused(vertices, pos, tri, uv, tex3, H, W, max_mip_level, shading)

    def __repr__(self) -> str:
        return f"TorchRasterizer(device={self.device})"
