"""The torch backend makes the normals and rast images only when they are read (the shape phase reads
neither); reading them gives the same images as the four-primitive reference pipeline."""

import sys
from pathlib import Path

import numpy as np
import torch

from saft.render.output import RenderOutput

sys.path.insert(0, str(Path(__file__).parent))
from _render_helpers import grid, pinhole, smooth_texture  # noqa: E402


def _jittered_sheet(generator: torch.Generator, dtype=torch.float32):
    """A 4 × 4-vertex sheet, jittered by 1 cm: vertices (1, 16, 3), triangles, uvs."""
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, 4), np.linspace(-0.3, 0.3, 4))
    verts = torch.tensor(np.stack([xs, ys, np.zeros_like(xs)], -1).reshape(-1, 3), dtype=dtype)
    verts = (verts + 0.01 * torch.randn(verts.shape, generator=generator, dtype=dtype))[None]
    quads = [(r * 4 + c, r * 4 + c + 1, r * 4 + c + 5, r * 4 + c + 4) for r in range(3) for c in range(3)]
    tri = torch.tensor([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=torch.int64)
    return verts, tri, (verts[0, :, :2] + 0.5).clamp(0, 1)


def _clip(verts: torch.Tensor) -> torch.Tensor:
    """An orthographic clip-space position of the sheet, filling most of the image."""
    return torch.cat([2.5 * verts[..., :2], 0.5 + 0 * verts[..., 2:], torch.ones_like(verts[..., :1])], dim=-1)


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
    verts, tri, uv = _jittered_sheet(g)
    pos = _clip(verts)
    tex = torch.rand(8, 8, 3, generator=g)
    fused = TorchRasterizer.render_cloth(verts, pos, tri, uv, tex, 24, 24, None)
    ref = render_cloth_primitives(TorchRasterizer(), verts, pos, tri, uv, tex, 24, 24, None)
    assert torch.allclose(fused.rgb, ref.rgb, atol=1e-5)
    covered = ref.rast[..., 3] > 0
    assert covered.float().mean() > 0.3
    assert torch.allclose(fused.normals[covered], ref.normals[covered], atol=1e-5)
    assert torch.allclose(fused.rast, ref.rast, atol=1e-5)


def test_fused_vertex_shading_matches_the_reference_in_value_and_gradient():
    """vertex_shading (per-vertex colour factors interpolated in the normals' slot): the fused path gives
    the reference pipeline's image and the same gradients to the factors and the vertices."""
    from saft.render.reference import render_cloth_primitives
    from saft.render.torch.rasterizer import TorchRasterizer

    g = torch.Generator().manual_seed(1)
    base, tri, uv = _jittered_sheet(g, torch.float64)
    tex = torch.rand(8, 8, 3, generator=g, dtype=torch.float64)
    shade0 = 0.5 + torch.rand(1, 16, 3, generator=g, dtype=torch.float64)
    weights = torch.rand(1, 24, 24, 3, generator=g, dtype=torch.float64)
    results = []
    for fn in (lambda *a: TorchRasterizer.render_cloth(*a),
               lambda *a: render_cloth_primitives(TorchRasterizer(), *a)):
        verts = base.clone().requires_grad_(True)
        shade = shade0.clone().requires_grad_(True)
        out = fn(verts, _clip(verts), tri, uv, tex, 24, 24, None, shade)
        (out.rgb * weights).sum().backward()
        results.append((out.rgb.detach(), shade.grad, verts.grad))
    (rgb_f, gs_f, gv_f), (rgb_r, gs_r, gv_r) = results
    unshaded = TorchRasterizer.render_cloth(base, _clip(base), tri, uv, tex, 24, 24, None)
    assert not torch.allclose(rgb_f, unshaded.rgb, atol=1e-3)   # the factors do change the image
    assert torch.allclose(rgb_f, rgb_r, atol=1e-9)
    assert gs_f.abs().sum() > 0
    assert torch.allclose(gs_f, gs_r, atol=1e-8)
    assert torch.allclose(gv_f, gv_r, atol=1e-8)
    try:
        unused = TorchRasterizer.render_cloth(base, _clip(base), tri, uv, tex, 24, 24, None, shade0).normals
    except ValueError as exc:
        assert "vertex_shading" in str(exc)
    else:
        raise AssertionError(f"normals of a shaded render should raise, got {unused.shape}")


def test_shading_ratio_is_one_without_light_and_follows_the_normal():
    from saft.render.shading import facing_normals, shading_ratio

    verts = torch.tensor([[0.0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=torch.float64)
    tri = torch.tensor([[0, 1, 2]])
    cam = torch.zeros(3, dtype=torch.float64)
    n0 = facing_normals(verts[None], tri, cam)[0]
    assert torch.allclose(n0, torch.tensor([0.0, 0, -1], dtype=torch.float64).expand(3, 3))  # towards the camera
    assert torch.equal(shading_ratio(verts, n0, tri, cam, torch.zeros(3)), torch.ones(1, 3, 3, dtype=torch.float64))
    # bring the top vertex towards the camera: the facing normal turns to -y, so a light from -y brightens
    # the triangle relative to frame 0 (whose normal is perpendicular to the light: irradiance 1)
    tilted = verts.clone()
    tilted[2, 2] = 0.5
    light = torch.tensor([0.0, -0.5, 0.0], dtype=torch.float64)
    r = shading_ratio(tilted, n0, tri, cam, light)
    n1 = facing_normals(tilted[None], tri, cam)[0, 0]
    assert n1[1] < -0.1
    assert torch.allclose(r, (1 - 0.5 * n1[1]).expand(1, 3, 3))
    assert (r > 1.1).all()


def test_the_light_is_recovered_from_images_of_a_turning_sheet():
    """Frames of a sheet turning about its top edge, shaded with a known light relative to frame 0: fitting
    the light alone through render_cloth(vertex_shading=shading_ratio(...)) finds it again."""
    from saft.render import render_cloth
    from saft.render.shading import facing_normals, shading_ratio

    verts, tris, uvs = grid(6, -0.2, 0.2, -0.2, 0.2, 1.0)
    v0 = torch.tensor(verts, dtype=torch.float64)
    frames = []
    for angle in (0.0, 0.3, -0.3, 0.6):   # turn about the top edge (y = -0.2), towards and away from the camera
        c, s = np.cos(angle), np.sin(angle)
        y, z = v0[:, 1] + 0.2, v0[:, 2] - 1.0
        frames.append(torch.stack([v0[:, 0], -0.2 + c * y - s * z, 1.0 + s * y + c * z], dim=-1))
    frames = torch.stack(frames)
    cam = pinhole(48, 48, 60.0)
    tri = torch.as_tensor(tris)
    tex = smooth_texture(16)
    center = torch.zeros(3, dtype=torch.float64)
    n0 = facing_normals(frames[:1], tri, center)[0]
    true_light = torch.tensor([0.2, -0.6, 0.3], dtype=torch.float64)

    def render(light):
        return render_cloth(frames, tri, uvs, tex, cam,
                            vertex_shading=shading_ratio(frames, n0, tri, center, light)).rgb

    with torch.no_grad():
        target = render(true_light)
    light = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([light], lr=0.05)
    for _ in range(150):
        opt.zero_grad()
        loss = ((render(light) - target) ** 2).mean()
        loss.backward()
        opt.step()
    # the component along the normals' plane of turning (y, z) is what the frames constrain
    assert torch.allclose(light.detach()[1:], true_light[1:], atol=0.05), light


def test_reference_pipeline_interpolates_normals_only_when_read():
    """The nvdiffrast backend's path (render_cloth_primitives) interpolates once per render; the normals image
    costs a second interpolate on first read, and its gradient reaches the vertices."""
    from saft.render.reference import render_cloth_primitives
    from saft.render.torch.rasterizer import TorchRasterizer

    class Counting(TorchRasterizer):
        calls = 0

        def interpolate(self, *args, **kwargs):
            Counting.calls += 1
            return super().interpolate(*args, **kwargs)

    g = torch.Generator().manual_seed(2)
    verts, tri, uv = _jittered_sheet(g)
    verts.requires_grad_(True)
    out = render_cloth_primitives(Counting(), verts, _clip(verts), tri, uv, torch.rand(8, 8, 3, generator=g),
                                  24, 24, None)
    assert Counting.calls == 1
    covered = out.rast[..., 3] > 0
    (out.normals[covered][:, 2] * torch.arange(int(covered.sum()))).sum().backward()
    assert Counting.calls == 2
    assert verts.grad.abs().sum() > 0
