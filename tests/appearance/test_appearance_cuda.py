"""Phase 3 on a GPU (Mitsuba's cuda_ad_rgb; skipped without CUDA or without Mitsuba): the same small fit as
test_appearance_fit.py's, scene rendered and maps fitted on the GPU, lowers the re-render error as clearly
as on the CPU. Where Mitsuba is installed and CUDA is present, a broken CUDA variant (no OptiX, a JIT
error) fails here rather than in a user's run."""

import importlib.util

import numpy as np
import pytest
import torch

from saft.appearance.fit import AppearanceResult, fit_appearance
from saft.synthetic.appearance import make_scene

from test_appearance_fit import _config, _rerender_error

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs an NVIDIA GPU"),
    pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="needs Mitsuba 3"),
]


def test_fit_on_the_gpu_lowers_rerender_error():
    sc = make_scene(n_frames=3, image_size=40, map_size=32, render_spp=64, device="cuda")
    cfg = _config(30)
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg, device="cuda")
    assert len(res.losses) == 30 and np.isfinite(res.losses).all()

    init = AppearanceResult(np.full_like(res.diffuse, 0.5), np.full_like(res.roughness, 0.5),
                            np.full_like(res.metallic, 0.5), np.full_like(res.envmap, 0.5), [], cfg)
    before, after = _rerender_error(init, sc, "cuda"), _rerender_error(res, sc, "cuda")
    print(f"re-render error on CUDA {before:.5f} -> {after:.5f} (ratio {before / after:.2f})")
    assert after < before / 2.5, (before, after)
