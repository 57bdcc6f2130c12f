"""Backend choice and the module-level primitives (dispatching on the tensors' device)."""

from __future__ import annotations

import torch

from saft.errors import BackendUnavailableError
from saft.render.nvdiffrast_backend import NvdiffrastRasterizer, nvdiffrast_available, nvdiffrast_status
from saft.render.torch import TorchRasterizer

_INSTANCES: dict = {}


def get_rasterizer(backend: str = "auto", device: str | torch.device | None = None):
    """A rasterizer object with .rasterize/.interpolate/.texture/.antialias (same signatures as the
    module-level functions of saft.render).

    backend: 'torch' (PyTorch, any device), 'nvdiffrast' (CUDA only; BackendUnavailableError saying why
    when it does not work here) or 'auto' (nvdiffrast when `device` is CUDA and nvdiffrast rasterizes a
    test triangle, saft.render.nvdiffrast_backend.nvdiffrast_status; else torch). device defaults to CPU.
    Instances are cached per (backend, device): nvdiffrast contexts are expensive to create.
    """
    device = torch.device("cpu" if device is None else device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    if backend == "auto":
        backend = "nvdiffrast" if device.type == "cuda" and nvdiffrast_available() else "torch"
    key = (backend, str(device))
    inst = _INSTANCES.get(key)
    if inst is not None:
        return inst
    if backend == "torch":
        inst = TorchRasterizer(device)
    elif backend == "nvdiffrast":
        if device.type != "cuda":
            raise ValueError("backend='nvdiffrast' needs a CUDA device")
        ok, why = nvdiffrast_status()
        if not ok:
            raise BackendUnavailableError(f"render.backend = 'nvdiffrast' does not work here ({why}); install "
                                          "it with pip install 'saft[cuda]' (diffrp-nvdiffrast) or use 'torch'")
        inst = NvdiffrastRasterizer(device)
    else:
        raise ValueError(f"unknown rasterizer backend {backend!r} (auto, torch, nvdiffrast)")
    _INSTANCES[key] = inst
    return inst


def _for(t: torch.Tensor):
    return get_rasterizer("auto", t.device)


def rasterize(pos, tri, resolution, with_db: bool = False):
    """rast (B, H, W, 4) = (u, v, z/w, triangle_id + 1), 0 where empty; (rast, rast_db) with with_db."""
    return _for(pos).rasterize(pos, tri, resolution, with_db=with_db)


def interpolate(attr, rast, tri, rast_db=None, diff_attrs=None):
    """Attributes (B|1, V, C) or (V, C) → (B, H, W, C); with rast_db → (out, out_da)."""
    return _for(rast).interpolate(attr, rast, tri, rast_db=rast_db, diff_attrs=diff_attrs)


def texture(tex, uv, uv_da=None, filter_mode="auto", boundary_mode="wrap", max_mip_level=None):
    """Bilinear / trilinear-mip-mapped lookup of tex (B|1, Ht, Wt, C) at uv (B, H, W, 2)."""
    return _for(uv).texture(tex, uv, uv_da, filter_mode=filter_mode, boundary_mode=boundary_mode,
                            max_mip_level=max_mip_level)


def antialias(color, rast, pos, tri):
    """Analytic antialiasing with silhouette gradients (boundary and fold edges) w.r.t. pos."""
    return _for(color).antialias(color, rast, pos, tri)
