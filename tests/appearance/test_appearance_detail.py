"""The detail share decided from the first frames: texels found on the surface, frames sampled into texture
space (hidden texels left out), a pattern that repeats told from noise that does not."""

import numpy as np
import pytest
import torch

from saft.appearance.detail import detail_share, first_frames_detail_share, project_to_texture, texel_triangles
from saft.appearance.guided import GuidedMaps, smooth_within_clusters
from saft.appearance.params import srgb_to_linear
from saft.scene.camera import look_at


def _sheet(n=5, size=0.4, z=0.0):
    """A flat n×n-vertex sheet in the plane z, facing +z, UVs spanning the unit square."""
    s = np.linspace(0.0, 1.0, n)
    u, v = np.meshgrid(s, s)
    uvs = np.stack([u.ravel(), v.ravel()], -1)
    verts = np.stack([(u.ravel() - 0.5) * size, (v.ravel() - 0.5) * size, np.full(n * n, z)], -1)
    quads = [(j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i) for j in range(n - 1) for i in range(n - 1)]
    tri = np.array([(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads])
    return verts, tri, uvs


def _camera(width=80, height=80, f=100.0):
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), K, width, height)


def test_texel_triangles_interpolate_each_texel_centre():
    verts, tri, uvs = _sheet()
    size = 32
    tri_of, bary = texel_triangles(tri, uvs, size)
    assert (tri_of >= 0).all()                       # the sheet's UVs cover the whole square
    assert np.allclose(bary.sum(-1), 1.0) and (bary > -1e-6).all()
    uv = (uvs[tri[tri_of]] * bary[..., None]).sum(-2)   # the UV each texel's barycentrics give back
    col, row = np.meshgrid(np.arange(size), np.arange(size))
    assert np.allclose(uv[..., 0], (col + 0.5) / size) and np.allclose(uv[..., 1], 1.0 - (row + 0.5) / size)
    half, _ = texel_triangles(tri[: len(tri) // 2], uvs, size)
    assert (half >= 0).mean() == pytest.approx(0.5, abs=0.1)


def test_projection_samples_the_image_where_the_surface_is_seen():
    """A sheet seen face-on: each texel gets the image at its projected point (a linear ramp reproduces
    the point's column); texels outside the mask, and a sheet hidden behind another, are not valid."""
    verts, tri, uvs = _sheet()
    cam = _camera()
    size = 32
    tri_of, bary = texel_triangles(tri, uvs, size)
    cols = np.broadcast_to(np.arange(cam.width, dtype=np.float64)[None, :, None], (cam.height, cam.width, 1))
    mask = np.ones((cam.height, cam.width))
    values, valid = project_to_texture(verts, tri, tri_of, bary, cam, cols, mask)
    points = (verts[tri[tri_of]] * bary[..., None]).sum(-2).reshape(-1, 3)
    px, _ = cam.project(points)
    assert valid.all()
    assert np.allclose(values[..., 0].ravel(), px[:, 0], atol=1e-6)
    mask[:, : cam.width // 2] = 0.0                   # the left half of the image is not cloth
    _, valid = project_to_texture(verts, tri, tri_of, bary, cam, cols, mask)
    assert 0.3 < valid.mean() < 0.6
    # one cloth of two layers (the left half of the UV square a sheet, the right half a smaller sheet in
    # front of it): the front layer hides the middle of the back one
    front, ftri, fuv = _sheet(size=0.2, z=0.2)
    both = np.concatenate([verts, front])
    both_tri = np.concatenate([tri, ftri + len(verts)])
    both_uv = np.concatenate([uvs * [0.5, 1.0], fuv * [0.5, 1.0] + [0.5, 0.0]])
    tri_of, bary = texel_triangles(both_tri, both_uv, size)
    _, valid = project_to_texture(both, both_tri, tri_of, bary, cam, cols, np.ones_like(mask))
    back = valid[:, : size // 2]
    assert valid[:, size // 2:].all()                                   # the front layer: all seen
    assert back[0, 0] and not back[size // 2, size // 4]                # the back one: corner seen, centre hidden
    assert 0.5 < back.mean() < 0.9


def _frames_in_texture_space(pattern_amp, noise_amp, n_frames, size=64, seed=0):
    """Two clusters (left, right half): frame f sees base colour + a fixed pattern of pattern_amp (left
    half only: a fine weave) + its own noise of noise_amp, under a shading that changes between frames."""
    rng = np.random.default_rng(seed)
    labels = np.zeros((size, size), np.int64)
    labels[:, size // 2:] = 1
    base = np.where(labels[..., None] == 0, 0.4, 0.2) * np.ones(3)
    weave = pattern_amp * np.sign(np.sin(np.arange(size) * np.pi / 2 + 0.3))[None, :, None] * (labels[..., None] == 0)
    frames = []
    for f in range(n_frames):
        shade = 1.0 + 0.2 * f
        values = shade * (base + weave + noise_amp * rng.standard_normal((size, size, 3)))
        frames.append((values, np.ones((size, size), bool)))
    texture = frames[0][0] / 1.0                        # the "phase-1 texture": frame 0 (its noise included)
    smooth = smooth_within_clusters(texture, labels, 2.0)
    return texture - smooth, smooth, labels, frames


def test_a_pattern_that_repeats_is_kept_and_noise_that_does_not_is_dropped():
    detail, smooth, labels, frames = _frames_in_texture_space(pattern_amp=0.05, noise_amp=0.01, n_frames=3)
    share = detail_share(detail, smooth, labels, frames, sigma=2.0)
    assert share[0] > 0.85        # the weave: the same in every frame
    assert share[1] < 0.1         # plain cloth: its detail is frame 0's noise, which no later frame repeats
    # more noise on the weave: a smaller share, about the weave's part of the detail's variance
    detail, smooth, labels, frames = _frames_in_texture_space(pattern_amp=0.02, noise_amp=0.02, n_frames=3)
    noisy = detail_share(detail, smooth, labels, frames, sigma=2.0)
    assert 0.3 < noisy[0] < 0.85 and noisy[1] < 0.1
    with pytest.raises(ValueError):
        detail_share(detail, smooth, labels, frames[:1], sigma=2.0)


def test_fixed_share_is_used_and_not_learnt():
    rng = np.random.default_rng(1)
    tex = np.clip(0.4 + 0.05 * rng.standard_normal((32, 32, 3)), 0.01, 1).astype(np.float32)
    tex[:, 16:] *= 0.3
    model = GuidedMaps(tex, size=32, gain_grid=2, clusters=2, smoothing=2.0)
    share = np.array([0.8, 0.1])[: model.num_clusters]
    model.fix_detail_share(share)
    assert not model.detail_logit.requires_grad
    expect = model.texture + model.detail * torch.einsum("k,khw->hw", torch.as_tensor(share, dtype=torch.float32),
                                                         model.members)[..., None]
    assert torch.allclose(model()["diffuse"], expect.clamp(0, 1), atol=1e-5)
    assert all(p is not model.detail_logit for p in model.parameters() if p.requires_grad)


def test_first_frames_share_of_a_still_woven_sheet():
    """End to end through the geometry: a still sheet whose texture is a weave, seen in three frames with
    independent noise: the weave's cluster keeps most of its detail."""
    verts, tri, uvs = _sheet()
    cam = _camera(160, 160, 200.0)
    rng = np.random.default_rng(2)
    size = 64
    tri_of, bary = texel_triangles(tri, uvs, size)
    points = (verts[tri[tri_of]] * bary[..., None]).sum(-2).reshape(-1, 3)
    col = np.arange(cam.width)
    weave = 0.15 * (np.sin(col * np.pi / 3) > 0)               # stripes 3 pixels wide
    clean = np.broadcast_to((0.3 + weave)[None, :, None], (cam.height, cam.width, 3))
    frames = np.stack([np.clip(clean + 0.005 * rng.standard_normal(clean.shape), 0, 1) for _ in range(3)])
    mask = np.ones(frames.shape[:3])
    # the phase-1 texture: frame 0 sampled at the texels (sRGB), as the texture phase would have fitted it
    px, _ = cam.project(points)
    tex = frames[0][np.clip(np.round(px[:, 1]).astype(int), 0, cam.height - 1),
                    np.clip(np.round(px[:, 0]).astype(int), 0, cam.width - 1)].reshape(size, size, 3)
    model = GuidedMaps(srgb_to_linear(tex), size=size, gain_grid=2, clusters=1, smoothing=3.0)
    share = first_frames_detail_share(model, np.stack([verts] * 3), tri, uvs, cam, frames, mask, 2, 3.0)
    assert share.shape == (model.num_clusters,) and share.max() > 0.7


@pytest.mark.parametrize("mode", ["prior", "fit"])
def test_fit_decides_the_detail_share_from_the_first_frames(mode):
    """In a fit: "prior" holds the share at the first frames' estimate, "fit" learns it from frames 1..n
    only (the other maps still learn from every frame). Default (detail_frames = 0): learnt as before."""
    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import fit_appearance
    from saft.appearance.params import linear_to_srgb
    from saft.synthetic.appearance import make_scene

    sc = make_scene(n_frames=3, image_size=32, map_size=32, render_spp=16)
    texture = linear_to_srgb(torch.as_tensor(sc.diffuse)).numpy()
    cfg = cpu_profile()
    cfg.epochs, cfg.frames_per_epoch, cfg.texel_size, cfg.image_scale = 4, 1, 64, 1.0
    cfg.detail_frames, cfg.detail_mode = 2, mode
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg, init_texture=texture)
    share = torch.sigmoid(res.state["model"]["detail_logit"])
    if mode == "prior":
        model = GuidedMaps(srgb_to_linear(texture), size=64, gain_grid=cfg.gain_grid, clusters=cfg.clusters,
                           smoothing=cfg.texture_smoothing)
        expect = first_frames_detail_share(model, sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, 2,
                                           cfg.texture_smoothing)
        assert np.allclose(share.numpy(), np.clip(expect, 1e-4, 1 - 1e-4), atol=1e-5)
    else:
        assert not torch.allclose(share, torch.full_like(share, 0.5))   # learnt, from its start at one half
