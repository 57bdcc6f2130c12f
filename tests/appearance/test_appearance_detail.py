"""Which frames teach the detail share: texels found on the surface, frames sampled into texture space (hidden
texels left out), a frame whose motion lines the texture's weave up told from one that does not."""

import numpy as np
import pytest
import torch

from saft.appearance.detail import (detail_repeat_per_frame, project_to_texture, texel_triangles,
                                   untrusted_detail_frames)
from saft.appearance.guided import GuidedMaps
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


def _woven_sheet_video(shifts, noise=0.005, weave=0.15, size=64, seed=2):
    """A still sheet whose texture is a weave (stripes 3 pixels wide), one frame per entry of `shifts`: the
    frame's mesh is the true one moved sideways by that many metres (a motion error), each frame with its
    own noise. Returns the GuidedMaps of frame 0's texture and what detail_repeat_per_frame needs."""
    verts, tri, uvs = _sheet()
    cam = _camera(160, 160, 200.0)
    rng = np.random.default_rng(seed)
    tri_of, bary = texel_triangles(tri, uvs, size)
    points = (verts[tri[tri_of]] * bary[..., None]).sum(-2).reshape(-1, 3)
    stripes = weave * (np.sin(np.arange(cam.width) * np.pi / 3) > 0)
    clean = np.broadcast_to((0.3 + stripes)[None, :, None], (cam.height, cam.width, 3))
    frames = np.stack([np.clip(clean + noise * rng.standard_normal(clean.shape), 0, 1) for _ in shifts])
    px, _ = cam.project(points)   # the phase-1 texture: frame 0 at the texels, as the texture phase fits it
    tex = frames[0][np.clip(np.round(px[:, 1]).astype(int), 0, cam.height - 1),
                    np.clip(np.round(px[:, 0]).astype(int), 0, cam.width - 1)].reshape(size, size, 3)
    model = GuidedMaps(srgb_to_linear(tex), size=size, gain_grid=2, clusters=1, smoothing=3.0)
    meshes = np.stack([verts + [dx, 0.0, 0.0] for dx in shifts])
    return model, meshes, tri, uvs, cam, frames, np.ones(frames.shape[:3])


def test_a_frame_whose_motion_misses_the_weave_repeats_little_of_it():
    """A weave seen in 4 frames: frames 1-2 with the right mesh repeat most of the texture's detail; frame 3,
    whose mesh is off by half a stripe (1.5 px = 7.5 mm), repeats little and is the one left out."""
    model, meshes, tri, uvs, cam, frames, mask = _woven_sheet_video([0.0, 0.0, 0.0, 0.0075])
    R = detail_repeat_per_frame(model, meshes, tri, uvs, cam, frames, mask, 3.0)
    assert R[0] == 1.0 and R[1] > 0.7 and R[2] > 0.7 and R[3] < 0.5 * R[1:3].mean()
    assert untrusted_detail_frames(model, meshes, tri, uvs, cam, frames, mask, 3.0, trust=0.5) == [3]
    assert untrusted_detail_frames(model, meshes, tri, uvs, cam, frames, mask, 3.0, trust=0.0) == []
    assert untrusted_detail_frames(model, meshes[:2], tri, uvs, cam, frames[:2], mask[:2], 3.0, trust=0.5) == []


def test_noise_is_not_a_pattern_and_no_frame_is_judged():
    """A plain sheet: the texture's detail is frame 0's noise, which no later frame repeats (R ≈ 0 below
    FLOOR), so even a frame with a wrong mesh is kept."""
    model, meshes, tri, uvs, cam, frames, mask = _woven_sheet_video([0.0, 0.0, 0.0, 0.0075], noise=0.03, weave=0.0)
    R = detail_repeat_per_frame(model, meshes, tri, uvs, cam, frames, mask, 3.0)
    assert np.abs(R[1:]).max() < 0.1
    assert untrusted_detail_frames(model, meshes, tri, uvs, cam, frames, mask, 3.0, trust=0.5) == []


@pytest.mark.parametrize("untrusted", [False, True])
def test_untrusted_frames_do_not_teach_the_detail_share(monkeypatch, tmp_path, untrusted):
    """A fit in which every frame is judged untrusted leaves the detail share where it started (one half)
    while the other maps learn; with none untrusted the share learns as before."""
    import saft.appearance.fit as fit_module
    from saft.appearance.fit import load_appearance, save_appearance
    from saft.appearance.config import cpu_profile
    from saft.appearance.params import linear_to_srgb
    from saft.synthetic.appearance import make_scene

    sc = make_scene(n_frames=3, image_size=32, map_size=32, render_spp=16)
    texture = linear_to_srgb(torch.as_tensor(sc.diffuse)).numpy()
    monkeypatch.setattr(fit_module, "untrusted_detail_frames",
                        lambda *a, **k: [0, 1, 2] if untrusted else [])
    cfg = cpu_profile()
    cfg.epochs, cfg.frames_per_epoch, cfg.texel_size, cfg.image_scale, cfg.detail_trust = 3, 2, 64, 1.0, 0.5
    res = fit_module.fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg,
                                    init_texture=texture)
    share = torch.sigmoid(res.state["model"]["detail_logit"])
    assert torch.allclose(share, torch.full_like(share, 0.5)) == untrusted
    assert not torch.allclose(res.state["model"]["gain"], torch.zeros(1))   # the rest learnt in both
    assert res.detail_frames_left_out == ([0, 1, 2] if untrusted else [])
    save_appearance(res, tmp_path)      # written into appearance.json, read back
    assert load_appearance(tmp_path).detail_frames_left_out == res.detail_frames_left_out
