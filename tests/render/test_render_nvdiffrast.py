"""nvdiffrast vs the PyTorch backend on the same scene. Skipped without CUDA or without the nvdiffrast package;
where both are there, nvdiffrast must work (a broken plugin build or import fails here, loudly).

Stated tolerance: identical coverage except on pixels whose centre lies within 1e-3 px of an edge;
barycentrics and z/w within 1e-4; rgb within 0.02 (mean 0.002) — the mip level formulas differ slightly —
mask within 0.05 on silhouette pixels (mean 0.002), depth within 1e-4 m; gradients w.r.t. vertices with
cosine similarity ≥ 0.95.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from saft.render import get_rasterizer, render_cloth
from saft.render.nvdiffrast_backend import nvdiffrast_status

sys.path.insert(0, str(Path(__file__).parent))
from _render_helpers import grid, pinhole, smooth_texture  # noqa: E402

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
              pytest.mark.skipif(importlib.util.find_spec("nvdiffrast") is None,
                                 reason="needs nvdiffrast (saft[cuda]: the diffrp-nvdiffrast package)")]


def test_nvdiffrast_rasterizes_on_this_gpu():
    ok, why = nvdiffrast_status()
    assert ok, f"nvdiffrast is installed but does not work: {why}"


def test_nvdiffrast_and_torch_backends_agree():
    dev = torch.device("cuda")
    cam = pinhole(96, 80, 100.0)
    verts, tris, uvs = grid(9, -0.35, 0.3, -0.25, 0.3, 1.0)
    verts[:, 2] += 0.15 * np.sin(6 * verts[:, 0]) + 0.1 * verts[:, 1]
    outs, grads = [], []
    for backend in ("torch", "nvdiffrast"):
        v = torch.tensor(verts, dtype=torch.float32, device=dev, requires_grad=True)
        tex = smooth_texture(64, torch.float32).to(dev).requires_grad_(True)
        o = render_cloth(v, tris, uvs, tex, cam, rasterizer=get_rasterizer(backend, dev))
        w = torch.linspace(0, 1, o.rgb.numel(), device=dev).reshape(o.rgb.shape)
        ((w * o.rgb).sum() + (w[..., 0] * o.mask).sum()).backward()
        outs.append(o)
        grads.append(v.grad)
    a, b = outs
    same = a.rast[..., 3] == b.rast[..., 3]
    assert same.float().mean() > 0.998
    cov = same & (a.rast[..., 3] > 0)
    assert (a.rast[..., :3][cov] - b.rast[..., :3][cov]).abs().max() < 1e-4
    assert (a.depth[cov] - b.depth[cov]).abs().max() < 1e-4
    assert (a.rgb - b.rgb).abs().max() < 0.02 and (a.rgb - b.rgb).abs().mean() < 2e-3
    assert (a.mask - b.mask).abs().max() < 0.05 and (a.mask - b.mask).abs().mean() < 2e-3
    g1, g2 = grads[0].reshape(-1), grads[1].reshape(-1)
    assert torch.dot(g1, g2) / (g1.norm() * g2.norm()) > 0.95
