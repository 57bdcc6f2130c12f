"""The texture refitted on several frames: shifted low-resolution frames recover a known texture better than
one frame does, each frame's gain stays out of the texture, the reference frame keeps gain 1 and no shift,
a mesh off by a fraction of a pixel is registered, and the frame choices."""

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from saft.appearance.params import linear_to_srgb, srgb_to_linear
from saft.appearance.texture_frames import (choose_texture_frames, fit_texture_frames, grid_at_vertices,
                                           keep_reference_shading, refit_texture)
from saft.render import render_cloth
from saft.scene.camera import look_at
from test_appearance_detail import _sheet, _woven_sheet_video   # a flat sheet facing +z; a woven one's video

SIZE = 48         # 1.5 texels per pixel: one frame's samples are too few for the texels


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One intra-op thread, as `saft reconstruct` runs phase 3 on a 2-core machine (run.threads = auto): these
    small fits took 75-83 s each with torch's two threads on a shared 2-core CPU, 4 s with one."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _camera(width=48, height=48, f=80.0):
    """The 0.4 m sheet spans 32 pixels."""
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), K, width, height)


def _texture(seed=0):
    """A known sRGB texture with detail down to a few texels (finer than one frame's pixels)."""
    rng = np.random.default_rng(seed)
    t = gaussian_filter(rng.standard_normal((SIZE, SIZE, 3)), sigma=(1.0, 1.0, 0))
    return np.clip(0.5 + 0.5 * t / t.std(), 0.05, 0.95).astype(np.float32)


def _video(texture, offsets_px, gains=None, noise=0.0, seed=1):
    """Frames of the sheet moved in the image plane by offsets_px (pixels; 1 px = depth / f metres), each
    frame's radiance times its gain, rendered as fit_texture_frames models them, with noise."""
    verts, tri, uvs = _sheet()
    cam = _camera()
    metres = 1.0 / cam.fx          # the camera looks down −z from 1 m: one pixel is 1 / f metres here
    meshes = np.stack([verts + [dx * metres, -dy * metres, 0.0] for dx, dy in offsets_px]).astype(np.float32)
    gains = np.ones(len(offsets_px)) if gains is None else np.asarray(gains)
    with torch.no_grad():
        out = render_cloth(torch.as_tensor(meshes), torch.as_tensor(tri, dtype=torch.int32),
                           torch.as_tensor(uvs, dtype=torch.float32), srgb_to_linear(torch.as_tensor(texture)), cam)
        rgb = linear_to_srgb(out.rgb * torch.as_tensor(gains, dtype=torch.float32)[:, None, None, None]).numpy()
    rng = np.random.default_rng(seed)
    rgb = np.clip(rgb + noise * rng.standard_normal(rgb.shape), 0.0, 1.0).astype(np.float32)
    return meshes, tri, uvs, cam, rgb, out.mask.numpy()


def _error(texture, truth):
    """RMS error over the texels the frames see well (a border of 4 texels left out)."""
    return float(np.sqrt(((texture - truth)[4:-4, 4:-4] ** 2).mean()))


# sub-pixel offsets of 8 frames: the quarter-pixel lattice the frames' samples interleave on
OFFSETS = [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5), (0.25, 0.75), (0.75, 0.25), (0.25, 0.25), (0.75, 0.75)]


def test_shifted_frames_recover_a_known_texture_better_than_one():
    truth = _texture()
    meshes, tri, uvs, cam, rgb, mask = _video(truth, OFFSETS, noise=0.01)
    start = np.full_like(truth, 0.5)
    kw = dict(epochs=300, lr=0.02, gain_grid=1, lambda_smooth=0.0)
    one, *_ = fit_texture_frames(meshes, tri, uvs, cam, rgb, mask, [0], start, **kw)
    many, gains, shifts, losses = fit_texture_frames(meshes, tri, uvs, cam, rgb, mask, range(8), start, **kw)
    e_one, e_many, e_start = _error(one, truth), _error(many, truth), _error(start, truth)
    assert e_one < 0.9 * e_start                         # one frame does learn the texture's coarse part
    assert e_many < 0.7 * e_one                          # eight shifted frames: the finer part and less noise
    assert losses[-1] < 0.2 * losses[0]
    assert shifts.shape == (8, 2, 1, 1) and not shifts.any()   # shift_grid = 0: no registration


def test_each_frames_gain_stays_out_of_the_texture():
    """Frames 1-3 darker or brighter by their own gains: the gains are recovered, the texture keeps frame
    0's brightness (a gain baked into it would scale it by their mean, 0.91), frame 0's gain stays 1."""
    truth = _texture(3)
    g = [1.0, 0.6, 0.8, 1.25]
    meshes, tri, uvs, cam, rgb, mask = _video(truth, OFFSETS[:4], gains=g)
    tex, gains, _, _ = fit_texture_frames(meshes, tri, uvs, cam, rgb, mask, range(4), truth * 0.9 + 0.05,
                                          epochs=300, lr=0.01, lr_gain=0.02, gain_grid=2, lambda_smooth=0.0)
    assert (gains[0] == 0.0).all()
    assert np.allclose(gains[1:].mean(axis=(1, 2, 3)), np.log(g[1:]), atol=0.03)
    ratio = srgb_to_linear(tex)[4:-4, 4:-4].mean() / srgb_to_linear(truth)[4:-4, 4:-4].mean()
    assert ratio == pytest.approx(1.0, abs=0.02)


def test_a_mesh_off_by_a_fraction_of_a_pixel_is_registered():
    """The frames moved by up to 0.6 px, the meshes given unmoved: without registration the texture is
    blurred by the misfit; with a 1×1 shift grid each frame's offset is found and the texture is better."""
    truth = _texture(5)
    offsets = [(0.0, 0.0), (0.6, 0.0), (0.0, -0.5), (-0.4, 0.4)]
    _, tri, uvs, cam, rgb, mask = _video(truth, offsets)
    still = np.repeat(_sheet()[0][None], len(offsets), 0)
    start = gaussian_filter(truth, sigma=(1.5, 1.5, 0))
    kw = dict(epochs=300, lr=0.01, gain_grid=1, lambda_smooth=0.0)
    plain, *_ = fit_texture_frames(still, tri, uvs, cam, rgb, mask, range(4), start, **kw)
    reg, _, shifts, _ = fit_texture_frames(still, tri, uvs, cam, rgb, mask, range(4), start, shift_grid=1,
                                           lr_shift=0.02, **kw)
    assert (shifts[0] == 0.0).all()
    # the shifts are in image pixels (x right, y down), as the offsets are
    found = shifts[1:, :, 0, 0]
    assert np.allclose(found, [(dx, dy) for dx, dy in offsets[1:]], atol=0.15)
    assert _error(reg, truth) < 0.8 * _error(plain, truth)


def test_grid_at_vertices_reads_the_uv_square_as_the_texture_image():
    """Row 0 of a grid is v = 1 (the texture image's top), column 0 is u = 0."""
    grid = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])     # (1, 1, 2, 2)
    uv = torch.tensor([[0.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0], [0.5, 0.5]])
    assert grid_at_vertices(grid, uv)[0, :, 0].tolist() == pytest.approx([1.0, 2.0, 3.0, 4.0, 2.5])


def test_frame_choices_start_at_frame_zero():
    truth = _texture()
    meshes, tri, uvs, cam, rgb, mask = _video(truth, [(0.0, 0.0)] * 6 + [(3.0, 0.0)] * 2)
    args = (truth, meshes, tri, uvs, cam, rgb, mask)
    assert choose_texture_frames("first", 4, *args) == [0, 1, 2, 3]
    assert choose_texture_frames("spread", 3, *args) == [0, 4, 7]
    assert choose_texture_frames("first", 20, *args) == list(range(8))
    with pytest.raises(ValueError):
        choose_texture_frames("best", 4, *args)


def test_the_option_is_validated():
    from saft.appearance.config import AppearanceConfig
    from saft.errors import SaftInputError

    AppearanceConfig(texture_frames=0).validate()
    AppearanceConfig(texture_frames=8).validate()
    for bad in (1, -2):
        with pytest.raises(SaftInputError):
            AppearanceConfig(texture_frames=bad).validate()


def test_keep_reference_shading_restores_the_low_frequencies_and_keeps_the_detail():
    """A texture darkened by a smooth ramp and given new fine detail: the ramp goes, the detail stays."""
    ref = _texture(7)
    ramp = np.linspace(0.6, 1.0, SIZE, dtype=np.float32)[None, :, None]
    detail = 0.05 * np.sign(np.sin(np.arange(SIZE) * np.pi / 1.5))[:, None, None].astype(np.float32)
    lin = np.clip(srgb_to_linear(ref) * ramp + detail, 0.0, 1.0)
    moved = linear_to_srgb(torch.as_tensor(lin)).numpy()
    kept = srgb_to_linear(keep_reference_shading(moved, ref, sigma=4.0))
    blur = lambda a: gaussian_filter(a, sigma=(4.0, 4.0, 0))
    inner = (slice(8, -8), slice(8, -8))
    off = np.abs(blur(kept) / blur(srgb_to_linear(ref)) - 1.0)[inner]
    assert off.mean() < 0.01 and off.max() < 0.08                                       # the ramp is gone
    assert np.abs(blur(lin) / blur(srgb_to_linear(ref)) - 1.0)[inner].max() > 0.3      # (it was there)
    fine = lambda a: a - blur(a)
    assert np.corrcoef(fine(kept)[inner].ravel(), fine(lin)[inner].ravel())[0, 1] > 0.95


def test_refit_leaves_a_plain_texture_alone_and_refits_a_woven_one():
    """The gate: a plain sheet's detail is frame 0's noise (frames 1-2 do not repeat it): the texture comes
    back unchanged and no frame is used. A woven sheet: refitted on the trusted frames, frame 3 (its mesh
    half a stripe off) left out."""
    plain, meshes, tri, uvs, cam, frames, mask = _woven_sheet_video([0.0, 0.0, 0.0, 0.0075], noise=0.03, weave=0.0)
    tex = linear_to_srgb(plain.texture + plain.detail).numpy()          # frame 0's texture, sRGB
    out, used = refit_texture(meshes, tri, uvs, cam, frames, mask, tex, 8, smoothing=3.0, clusters=1)
    assert used == [] and np.array_equal(out, tex)
    woven, meshes, tri, uvs, cam, frames, mask = _woven_sheet_video([0.0, 0.0, 0.0, 0.0075])
    tex = linear_to_srgb(woven.texture + woven.detail).numpy()
    out, used = refit_texture(meshes, tri, uvs, cam, frames, mask, tex, 4, smoothing=3.0, clusters=1)
    assert used == [0, 1, 2] and out.shape == tex.shape and not np.array_equal(out, tex)
    # asked for 8, three trusted frames are fewer than half: the texture is kept
    out, used = refit_texture(meshes, tri, uvs, cam, frames, mask, tex, 8, smoothing=3.0, clusters=1)
    assert used == [] and np.array_equal(out, tex)
