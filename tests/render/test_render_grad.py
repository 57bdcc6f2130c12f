"""Gradients: image and mask losses w.r.t. vertex positions against finite differences of a supersampled
render, on a mesh-boundary silhouette and on a fold silhouette; texture gradients exact; barycentric
backward against autograd."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from saft.render import render_cloth
from saft.render.torch import antialias as aa
from saft.render.torch import fused, fused_texture, raster
from saft.render.torch import interpolate as interp
from saft.render.torch import texture as texmod
from saft.render.torch.rows import ScatterPlanar

sys.path.insert(0, str(Path(__file__).parent))
from _render_helpers import box_down, folded_sheet, grid, pinhole, smooth_texture  # noqa: E402

SS = 12  # supersampling factor of the reference


def _weights(shape, seed):
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(shape, generator=g, dtype=torch.float64)
    # smooth it a little so the reference is not dominated by single-pixel noise
    w = torch.nn.functional.avg_pool2d(w.permute(0, 3, 1, 2), 3, 1, 1, count_include_pad=False)
    return w.permute(0, 2, 3, 1)


def _fd_check(verts, tris, uvs, cam, moving, which, seed=0, h=2e-3):
    tex = smooth_texture()
    W_rgb = _weights((1, cam.height, cam.width, 3), seed)
    W_mask = W_rgb[..., 0]

    def loss_of(out, ss=1):
        rgb, mask = out.rgb, out.mask
        if ss > 1:
            rgb = box_down(rgb, ss)
            mask = box_down(mask[..., None], ss)[..., 0]
        return (W_rgb * rgb).sum() if which == "image" else (W_mask * mask).sum()

    v = torch.tensor(verts, requires_grad=True)
    loss_of(render_cloth(v, tris, uvs, tex, cam)).backward()
    grad = v.grad[moving].clone()

    big = cam.scaled(SS)
    fd = torch.zeros_like(grad)
    for a, vi in enumerate(moving):
        for c in range(2):  # image-plane directions (the scenes face the camera)
            vp, vm = verts.copy(), verts.copy()
            vp[vi, c] += h
            vm[vi, c] -= h
            lp = loss_of(render_cloth(torch.tensor(vp), tris, uvs, tex, big), SS)
            lm = loss_of(render_cloth(torch.tensor(vm), tris, uvs, tex, big), SS)
            fd[a, c] = (lp - lm) / (2 * h)
    g, f = grad[:, :2].reshape(-1), fd[:, :2].reshape(-1)
    cos = torch.dot(g, f) / (g.norm() * f.norm())
    rel = (g - f).norm() / f.norm()
    return g, f, float(cos), float(rel)


def test_mask_and_image_gradients_on_a_boundary_silhouette():
    cam = pinhole(32, 28, 40.0)
    verts, tris, uvs = grid(3, -0.21, 0.19, -0.17, 0.16, 1.0)
    moving = [2, 5, 8]  # the right column: boundary edge
    for which in ("mask", "image"):
        g, f, cos, rel = _fd_check(verts, tris, uvs, cam, moving, which)
        assert f.norm() > 1.0, "the finite difference must see the silhouette move"
        assert cos > 0.97 and rel < 0.25, (which, g, f)


def test_mask_and_image_gradients_on_a_fold_silhouette():
    verts, tris, uvs, fold = folded_sheet()
    cam = pinhole(32, 28, 40.0)
    sil = aa.silhouette_edges(_clip(verts, cam), torch.tensor(tris), cam.height, cam.width)
    # the fold column is an interior edge of the mesh, yet a silhouette
    assert sil.any(-1)[0].sum() > 0
    for which in ("mask", "image"):
        g, f, cos, rel = _fd_check(verts, tris, uvs, cam, fold, which, seed=1)
        assert f.norm() > 1.0
        assert cos > 0.95 and rel < 0.4, (which, g, f)  # measured: cos 0.97, rel 0.29 (corners of the fold)
        # without fold silhouettes there would be no gradient to the fold vertices at all
        assert g.norm() > 0.5 * f.norm()


def _clip(verts, cam):
    from saft.render import camera_to_clip
    return camera_to_clip(torch.tensor(verts)[None], cam)


def test_texture_gradient_is_exact():
    """The rendered colour is linear in the texture: the gradient equals the finite difference exactly."""
    cam = pinhole(20, 18, 25.0)
    verts, tris, uvs = grid(3, -0.3, 0.28, -0.25, 0.3, 1.0)
    verts[:, 2] += 0.2 * verts[:, 0]
    tex = smooth_texture(32).requires_grad_(True)
    W = _weights((1, 18, 20, 3), 3)
    loss = (W * render_cloth(torch.tensor(verts), tris, uvs, tex, cam).rgb).sum()
    loss.backward()
    rng = np.random.default_rng(0)
    for _ in range(12):
        i, j, c = rng.integers(0, 32), rng.integers(0, 32), rng.integers(0, 3)
        t2 = tex.detach().clone()
        t2[i, j, c] += 1.0
        l2 = (W * render_cloth(torch.tensor(verts), tris, uvs, t2, cam).rgb).sum()
        assert float(l2 - loss.detach()) == pytest.approx(float(tex.grad[i, j, c]), abs=1e-10)
    assert tex.grad.abs().sum() > 0
    # a texel's gradient through the mip pyramid: total weight is the rendered coverage
    total = (W * render_cloth(torch.tensor(verts), tris, uvs, torch.ones_like(tex), cam).rgb).sum()
    assert float(tex.grad.sum()) == pytest.approx(float(total), rel=1e-10)


def test_barycentric_and_texture_backward_match_autograd():
    torch.manual_seed(0)
    pos = torch.rand(2, 10, 4, dtype=torch.float64)
    pos[..., 3] += 1.0
    pos[..., :2] = pos[..., :2] * 2 - 1
    pos.requires_grad_(True)
    tri = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 2, 9]])
    pix = torch.tensor([3, 50, 77, 130, 199])
    tid = torch.tensor([0, 1, 2, 3, 1])
    assert torch.autograd.gradcheck(lambda p: raster.bary_weights(p, tri, pix, tid, (10, 10))[:2], (pos,))
    tex = torch.rand(8, 6, 2, dtype=torch.float64, requires_grad=True)
    uv = torch.rand(7, 2, dtype=torch.float64, requires_grad=True)
    da = torch.rand(7, 4, dtype=torch.float64) * 0.5
    for mode in ("clamp", "wrap"):
        assert torch.autograd.gradcheck(lambda t, u: texmod.texture_compact(t, u, da, mode), (tex, uv))
    A = torch.rand(10, 3, dtype=torch.float64, requires_grad=True)
    bw = torch.rand(3, 5, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 10, (3, 5))
    assert torch.autograd.gradcheck(lambda b, a: interp.interp_compact(b, a, idx), (bw, A))


@pytest.mark.parametrize("numba", [True, False], ids=["numba", "torch"])
@pytest.mark.parametrize("shape", [(8, 6), (16, 16), (5, 1), (1, 4), (33, 17)])
def test_fast_texture_matches_grid_sample_path(shape, numba, monkeypatch):
    """texture_fast (render_cloth's SoA kernel; on CPU the numba loops, or the torch ops CUDA runs) =
    texture_compact (grid_sample per mip level), clamp mode, in value and in gradient to texels and
    coordinates, for bilinear, trilinear and capped mip levels."""
    monkeypatch.setattr(fused_texture, "USE_NUMBA", numba)
    torch.manual_seed(sum(shape))
    Ht, Wt = shape
    tex = torch.rand(Ht, Wt, 3, dtype=torch.float64, requires_grad=True)
    uv = (torch.rand(60, 2, dtype=torch.float64) * 1.2 - 0.1).requires_grad_(True)
    for scale in (0.0, 0.02, 0.3, 2.0):
        da = torch.rand(60, 4, dtype=torch.float64) * scale
        for mml in (None, 1):
            ref = texmod.texture_compact(tex, uv, da if scale else None, "clamp", mml)
            got = fused.texture_fast(tex, uv[:, 0], uv[:, 1], da.T if scale else None, mml).T
            w = torch.rand_like(ref)
            g_ref = torch.autograd.grad((ref * w).sum(), (tex, uv))
            g_got = torch.autograd.grad((got * w).sum(), (tex, uv))
            torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)
            torch.testing.assert_close(g_got[0], g_ref[0], atol=1e-12, rtol=0)
            torch.testing.assert_close(g_got[1], g_ref[1], atol=1e-10, rtol=0)
    # a texture in another dtype than the coordinates (render_cloth allows it)
    u32 = uv.detach()[:, 0].float().requires_grad_(True)
    got = fused.texture_fast(tex, u32, uv.detach()[:, 1].float(), None)
    (got * torch.rand_like(got)).sum().backward()
    assert u32.grad.dtype == torch.float32 and tex.grad.dtype == torch.float64
    tex.grad = None
    u = uv.detach()[:7, 0].clone().requires_grad_(True)
    v = uv.detach()[:7, 1].clone().requires_grad_(True)
    da = torch.rand(4, 7, dtype=torch.float64) * 0.5
    assert torch.autograd.gradcheck(lambda t, a, b: fused.texture_fast(t, a, b, da), (tex, u, v))


def test_plane_table_matches_barycentrics_and_its_backward_is_exact():
    torch.manual_seed(1)
    B, V = 2, 10
    pos = torch.rand(B, V, 4, dtype=torch.float64)
    pos[..., 3] += 1.0
    pos[..., :2] = pos[..., :2] * 2 - 1
    tri = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 2, 9]])
    uv = torch.rand(V, 2, dtype=torch.float64)
    nrm = torch.rand(B, V, 3, dtype=torch.float64)
    pix = torch.tensor([3, 50, 77, 130, 199])
    tid = torch.tensor([0, 1, 2, 3, 1])
    H = W = 10
    b = pix // (H * W)
    nx, ny = raster.pixel_ndc(pix, H, W, torch.float64)
    table = fused.plane_table(pos, tri, uv, nrm)
    uv_p, depth, n, bw, zw, uv_da = fused.plane_interp(table, b * tri.shape[0] + tid, nx, ny, H, W)
    bw_ref, zw_ref, db = raster.bary_weights(pos, tri, pix, tid, (H, W), with_db=True)
    torch.testing.assert_close(bw, bw_ref[:2])
    torch.testing.assert_close(zw, zw_ref)
    vid = raster.pixel_vertex_ids(pos, tri, pix, tid, H, W)
    attr = torch.cat([uv[None].expand(B, V, 2), pos[..., 3:4], nrm], -1).reshape(B * V, 6)
    ref = interp.interp_compact(bw_ref, attr, vid)
    torch.testing.assert_close(torch.cat([uv_p, depth[None], n]).T, ref)
    a = uv[tri[tid]]  # (P, 3, 2): uv_da from the barycentric derivatives
    d0, d1 = a[:, 0] - a[:, 2], a[:, 1] - a[:, 2]
    ref_da = torch.stack([d0[:, 0] * db[0] + d1[:, 0] * db[2], d0[:, 0] * db[1] + d1[:, 0] * db[3],
                          d0[:, 1] * db[0] + d1[:, 1] * db[2], d0[:, 1] * db[1] + d1[:, 1] * db[3]])
    torch.testing.assert_close(uv_da, ref_da)
    # the backward (through the table to positions and normals), for every subset of differentiable outputs
    idx = b * tri.shape[0] + tid
    p0 = pos.clone().requires_grad_(True)
    n0 = nrm.clone().requires_grad_(True)
    for outs in ((0,), (0, 1), (0, 1, 2), (2,)):
        assert torch.autograd.gradcheck(
            lambda p, q: tuple(fused.plane_interp(fused.plane_table(p, tri, uv, q), idx, nx, ny, H, W)[k]
                               for k in outs), (p0, n0))


def test_antialias_blend_backward_is_exact():
    """The antialias blend's hand-written backward (to the colours and to the crossing offsets f, through
    which the silhouette gradients reach the positions) by gradcheck, targets repeating across the two
    axes as they can; and the whole antialias against gradcheck with respect to the colours."""
    from saft.render import antialias, camera_to_clip, rasterize
    g = torch.Generator().manual_seed(0)
    color = torch.rand(30, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    f = (torch.rand(12, dtype=torch.float64, generator=g) - 0.5).requires_grad_(True)
    pf = torch.randint(0, 30, (12,), generator=g)
    po = (pf + 1) % 30
    target = torch.where(f.detach() > 0, po, pf)
    target[6:] = target[:6]  # repeated targets
    assert torch.autograd.gradcheck(lambda c, x: aa._AABlendFn.apply(c, x, pf, po, target), (color, f))
    # render_cloth's split form (rgb and coverage as two tensors) is the same blend
    rgb, last = color.detach()[:, :2].clone(), color.detach()[:, 2].clone()
    r2, l2 = aa._AABlendSplitFn.apply(rgb, last, f.detach(), pf, po, target)
    whole = aa._AABlendFn.apply(color.detach(), f.detach(), pf, po, target)
    torch.testing.assert_close(torch.cat([r2, l2[:, None]], 1), whole)
    assert torch.autograd.gradcheck(lambda r, c, x: aa._AABlendSplitFn.apply(r, c, x, pf, po, target),
                                    (rgb.requires_grad_(True), last.requires_grad_(True), f))
    assert torch.autograd.gradcheck(lambda r, x: aa._AABlendSplitFn.apply(r, last.detach(), x, pf, po, target)[0],
                                    (rgb, f))
    vals = torch.rand(3, 5, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: ScatterPlanar.apply(x, torch.tensor([7, 1, 3, 0, 9]), 10), (vals,))
    verts, tris, _, _ = folded_sheet()
    cam = pinhole(16, 14, 20.0)
    tri = torch.tensor(tris)
    pos = camera_to_clip(torch.tensor(verts)[None], cam).detach()
    rast = rasterize(pos, tri, (cam.height, cam.width))
    img = torch.rand(1, cam.height, cam.width, 2, dtype=torch.float64, generator=g)
    assert not torch.equal(antialias(img, rast, pos, tri), img)
    assert torch.autograd.gradcheck(lambda c: antialias(c, rast, pos, tri), (img.requires_grad_(True),))


def test_fast_texture_pyramid_cache_sees_in_place_changes():
    """A texture without gradient keeps its mip pyramid between calls; an in-place change makes a new one."""
    torch.manual_seed(3)
    tex = torch.rand(32, 32, 3, dtype=torch.float64)
    u, v = torch.rand(50, dtype=torch.float64), torch.rand(50, dtype=torch.float64)
    da = torch.full((4, 50), 0.2, dtype=torch.float64)  # footprint of several texels: coarser levels in use
    first = fused.texture_fast(tex, u, v, da)
    torch.testing.assert_close(fused.texture_fast(tex, u, v, da), first, atol=0, rtol=0)
    tex.mul_(0.5)
    torch.testing.assert_close(fused.texture_fast(tex, u, v, da), fused.texture_fast(tex.clone(), u, v, da),
                               atol=0, rtol=0)
    torch.testing.assert_close(fused.texture_fast(tex, u, v, da), 0.5 * first, atol=1e-15, rtol=0)


def test_numba_and_torch_lookups_agree_in_float32_and_keep_a_changing_textures_gradient(monkeypatch):
    """The two CPU paths of texture_fast on a render's float32 texture and float64 coordinates, in value and
    in every gradient; with a texture that has a gradient (its pyramid in a rewritten workspace) a second
    lookup before the first one's backward must not change the first one's gradient."""
    torch.manual_seed(5)
    tex = torch.rand(64, 48, 3, requires_grad=True)
    u = (torch.rand(500, dtype=torch.float64) * 1.1 - 0.05).requires_grad_(True)
    v = (torch.rand(500, dtype=torch.float64) * 1.1 - 0.05).requires_grad_(True)
    da = torch.rand(4, 500, dtype=torch.float64) * 0.05
    w = torch.rand(3, 500)
    results = []
    for numba in (True, False):
        monkeypatch.setattr(fused_texture, "USE_NUMBA", numba)
        out = fused.texture_fast(tex, u, v, da)
        other = fused.texture_fast(tex * 0.5, v, u, da)  # rewrites the pyramid workspace
        results.append((out, *torch.autograd.grad((out * w).sum(), (tex, u, v))))
        del other
    for got, ref in zip(*results):
        torch.testing.assert_close(got, ref, atol=2e-6, rtol=1e-5)
