"""The torch backend makes the normals and rast images only when they are read (the shape phase reads
neither); reading them gives the same images as the four-primitive reference pipeline."""

import numpy as np
import torch

from saft.render.output import RenderOutput


def test_render_output_makes_a_lazy_image_once():
    calls = []

    def make():
        calls.append(1)
        return torch.ones(1, 2, 2, 3)

    out = RenderOutput(rgb=torch.zeros(1, 2, 2, 3), mask=torch.zeros(1, 2, 2), depth=torch.zeros(1, 2, 2),
                       normals=make, rast=torch.zeros(1, 2, 2, 4), pos_clip=torch.zeros(1, 3, 4))
    assert not calls
    assert torch.equal(out.normals, torch.ones(1, 2, 2, 3))
    assert torch.equal(out.normals, torch.ones(1, 2, 2, 3))
    assert len(calls) == 1
    assert out.rast.shape == (1, 2, 2, 4)


def test_fused_normals_and_rast_on_demand_match_the_reference():
    from saft.render.reference import render_cloth_primitives
    from saft.render.torch.rasterizer import TorchRasterizer

    g = torch.Generator().manual_seed(0)
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, 4), np.linspace(-0.3, 0.3, 4))
    verts = torch.tensor(np.stack([xs, ys, np.zeros_like(xs)], -1).reshape(-1, 3), dtype=torch.float32)
    verts = (verts + 0.01 * torch.randn(verts.shape, generator=g))[None]
    quads = [(r * 4 + c, r * 4 + c + 1, r * 4 + c + 5, r * 4 + c + 4) for r in range(3) for c in range(3)]
    tri = torch.tensor([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=torch.int64)
    uv = (verts[0, :, :2] + 0.5).clamp(0, 1)
    pos = torch.cat([2.5 * verts[..., :2], 0.5 + 0 * verts[..., 2:], torch.ones_like(verts[..., :1])], dim=-1)
    tex = torch.rand(8, 8, 3, generator=g)
    fused = TorchRasterizer.render_cloth(verts, pos, tri, uv, tex, 24, 24, None)
    ref = render_cloth_primitives(TorchRasterizer(), verts, pos, tri, uv, tex, 24, 24, None)
    assert torch.allclose(fused.rgb, ref.rgb, atol=1e-5)
    covered = ref.rast[..., 3] > 0
    assert covered.float().mean() > 0.3
    assert torch.allclose(fused.normals[covered], ref.normals[covered], atol=1e-5)
    assert torch.allclose(fused.rast, ref.rast, atol=1e-5)
