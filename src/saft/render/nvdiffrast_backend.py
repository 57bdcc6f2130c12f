"""The nvdiffrast backend (CUDA only): the same four primitives, delegated to nvdiffrast.

Installed through the optional extra (``diffrp-nvdiffrast``, which JIT-compiles its CUDA plugin on first
use); imported lazily so that saft imports without it. Inputs are converted to what nvdiffrast needs
(contiguous float32 on the GPU, int32 triangles) and outputs keep nvdiffrast's layout, which is also the
torch backend's: with saft's clip space (y_ndc = −1 at the top row, see saft.render.clip) row 0 of every
output is the top of the image.
"""

from __future__ import annotations

import functools
import sys

import torch

from saft.render.output import RenderOutput
from saft.render.reference import render_cloth_primitives
from saft.render.topology import TensorCache, topology


def load_nvdiffrast():
    """``nvdiffrast.torch`` with its CUDA plugin built (on first use, ~30 s) and importable.

    nvdiffrast builds its plugin with torch.utils.cpp_extension.load and then imports it by name; torch
    >= 2.11 no longer puts the extension's build folder on sys.path, so that import fails
    (ModuleNotFoundError: nvdiffrast_plugin_..._torch2_11_0_cu130). The build folder is put on sys.path
    first, the plugin is built or loaded, and the module is returned.
    """
    import nvdiffrast
    import nvdiffrast.torch as dr
    from nvdiffrast.torch import ops
    from torch.utils import cpp_extension

    name = ops.sanitize_name(f"nvdiffrast_plugin_{nvdiffrast.__version__}_torch{torch.__version__}")
    build_dir = cpp_extension._get_build_directory(name, False)
    if build_dir not in sys.path:
        sys.path.append(build_dir)
    ops._get_plugin()
    return dr


@functools.cache
def nvdiffrast_status() -> tuple[bool, str]:
    """(True, "") when nvdiffrast rasterizes a triangle on this machine's GPU, else (False, why not).
    Checked once per process: the import, the plugin build, a context and one rasterization."""
    if not torch.cuda.is_available():
        return False, "no CUDA device"
    try:
        dr = load_nvdiffrast()
        ctx = dr.RasterizeCudaContext(device=torch.device("cuda"))
        pos = torch.tensor([[[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0]]],
                           dtype=torch.float32, device="cuda")
        tri = torch.tensor([[0, 1, 2]], dtype=torch.int32, device="cuda")
        rast, _ = dr.rasterize(ctx, pos, tri, resolution=[16, 16])
        covered = int((rast[..., 3] > 0).sum())
    except Exception as exc:   # ImportError, a failed plugin build, a CUDA error: say which
        first = str(exc).strip().splitlines()
        return False, f"{type(exc).__name__}: {first[0] if first else ''}"[:300]
    # The triangle spans half the viewport in x and y: an eighth of the 256 pixels (32; measured on an H200).
    if not 26 <= covered <= 38:
        return False, f"a test triangle covered {covered} of 256 pixels instead of 32"
    return True, ""


def nvdiffrast_available() -> bool:
    """Whether nvdiffrast works here (nvdiffrast_status, without the reason)."""
    return nvdiffrast_status()[0]


class NvdiffrastRasterizer:
    """dr.RasterizeCudaContext on `device` plus the four ops. The int32 triangles and the antialias topology
    hash are made once per triangle list (saft.render.topology): a render then does no host sync for them."""

    name = "nvdiffrast"

    def __init__(self, device: str | torch.device = "cuda"):
        dr = load_nvdiffrast()
        self.device = torch.device(device)
        if self.device.type != "cuda":
            raise ValueError(f"the nvdiffrast backend needs a CUDA device, got {self.device}")
        self._dr = dr
        self.ctx = dr.RasterizeCudaContext(device=self.device)
        self._mips = TensorCache(limit=4)  # a few textures' mip stacks at most: see _mip

    def _tri(self, tri: torch.Tensor) -> torch.Tensor:
        return topology(tri, self.device).tri32

    def render_cloth(self, vertices: torch.Tensor, pos: torch.Tensor, tri: torch.Tensor, uv: torch.Tensor,
                     tex: torch.Tensor, H: int, W: int, max_mip_level: int | None,
                     shading: torch.Tensor | None = None) -> RenderOutput:
        """saft.render.render_cloth's backend call (arguments prepared there): the four primitives."""
        return render_cloth_primitives(self, vertices, pos, tri, uv, tex, H, W, max_mip_level, shading)

    def rasterize(self, pos: torch.Tensor, tri: torch.Tensor, resolution, with_db: bool = False):
        if pos.dim() == 2:
            pos = pos[None]
        rast, rast_db = self._dr.rasterize(self.ctx, pos.float().contiguous(), self._tri(tri),
                                           resolution=[int(resolution[0]), int(resolution[1])], grad_db=with_db)
        return (rast, rast_db) if with_db else rast

    def interpolate(self, attr, rast, tri, rast_db=None, diff_attrs=None):
        out, out_da = self._dr.interpolate(attr.float().contiguous(), rast, self._tri(tri), rast_db=rast_db,
                                           diff_attrs=diff_attrs)
        if rast_db is None:
            return out
        return out, (out_da if diff_attrs is not None else None)

    def texture(self, tex, uv, uv_da=None, filter_mode="auto", boundary_mode="wrap", max_mip_level=None,
                mask=None):
        if tex.dim() == 3:
            tex = tex[None]
        tex = tex.float().contiguous()
        mip = None
        if uv_da is not None and "mipmap" in filter_mode and not tex.requires_grad:
            mip = self._mip(tex, max_mip_level, boundary_mode == "cube")
        return self._dr.texture(tex, uv.float().contiguous(), None if uv_da is None else uv_da.float().contiguous(),
                                mip=mip, filter_mode=filter_mode, boundary_mode=boundary_mode,
                                max_mip_level=max_mip_level)

    def _mip(self, tex: torch.Tensor, max_mip_level, cube: bool):
        """nvdiffrast's mip stack of a texture that needs no gradient, made once per texture: the shape phase
        renders every frame with the same texture, and nvdiffrast otherwise rebuilds the stack (a kernel per
        level) in every call. Found by the identity of the tensor that owns the texels (TensorCache; its
        views share its _version)."""
        owner = tex if tex._base is None else tex._base
        key = (tex.storage_offset(), tuple(tex.shape), tuple(tex.stride()), max_mip_level, cube)
        mip = self._mips.get(owner, *key)
        if mip is None:
            mip = self._mips.put(owner, self._dr.texture_construct_mip(tex, max_mip_level, cube), *key)
        return mip

    def antialias(self, color, rast, pos, tri):
        if pos.dim() == 2:
            pos = pos[None]
        topo = topology(tri, self.device)
        cache = topo.backend_cache
        if "nvdiffrast_hash" not in cache:
            cache["nvdiffrast_hash"] = self._dr.antialias_construct_topology_hash(topo.tri32)
        return self._dr.antialias(color.float().contiguous(), rast, pos.float().contiguous(), topo.tri32,
                                  topology_hash=cache["nvdiffrast_hash"])

    def __repr__(self) -> str:
        return f"NvdiffrastRasterizer(device={self.device})"
