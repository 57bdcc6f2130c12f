"""A small appearance fit lowers the re-render error clearly; checkpoints resume; results save and load."""

import numpy as np
import pytest

from saft.appearance.config import cpu_profile
from saft.appearance.fit import (AppearanceResult, fit_appearance, load_appearance,
                                 render_appearance, save_appearance)
from saft.synthetic.appearance import make_scene
from saft.scene.camera import orbit_camera


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_frames=3, image_size=40, map_size=32, render_spp=64)


def _config(epochs):
    cfg = cpu_profile()   # the plain-texel parametrisation (the guided one: test_appearance_guided.py)
    cfg.maps, cfg.texel_size, cfg.env_levels, cfg.env_height, cfg.env_width = "texels", 128, 1, 64, 128
    cfg.lr_final_factor = 1.0
    cfg.epochs = epochs
    cfg.image_scale = 1.0
    cfg.frames_per_epoch = 2
    cfg.checkpoint_every = 5
    return cfg


def _rerender_error(res, sc, device="cpu"):
    imgs = render_appearance(res, sc.vertices, sc.triangles, sc.uvs, sc.camera, spp=32, device=device)
    m = sc.mask[..., None]
    return float(((imgs - sc.rgb) ** 2 * m).sum() / m.sum() / 3)


def test_fit_lowers_rerender_error(scene):
    sc = scene
    cfg = _config(30)
    seen = []
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg,
                         progress=lambda e, n, loss: seen.append((e, n)))
    assert seen[-1] == (30, 30) and len(res.losses) == 30 and np.isfinite(res.losses).all()
    assert res.envmap.shape == (256, 512, 3) and res.envmap.min() >= 0.01
    assert res.roughness.min() >= 1e-3
    init = AppearanceResult(np.full_like(res.diffuse, 0.5), np.full_like(res.roughness, 0.5),
                            np.full_like(res.metallic, 0.5), np.full_like(res.envmap, 0.5), [], cfg)
    before, after = _rerender_error(init, sc), _rerender_error(res, sc)
    print(f"re-render error {before:.5f} -> {after:.5f} (ratio {before / after:.2f})")
    assert after < before / 2.5, (before, after)


def test_decoder_fit_checkpoints_resume_and_save(scene, tmp_path):
    sc = scene
    cfg = _config(6)
    cfg.maps = "decoder"
    cfg.checkpoint_every = 3
    cfg.grey_fraction, cfg.blend_fraction = 1.0, 0.0  # the whole run in the grey phase
    states = []
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg, checkpoint=states.append)
    assert res.diffuse.shape == (112, 112, 3)  # 16 tiles of 32 px with 4 px overlap (cpu_profile)
    assert [s["epoch"] for s in states] == [3, 6]
    # grey phase: the fitted env map has no hue, yet its brightness was optimised
    assert np.allclose(res.envmap[..., 0], res.envmap[..., 1]) and np.allclose(res.envmap[..., 1], res.envmap[..., 2])
    assert np.abs(res.envmap - 0.5).max() > 1e-3
    # resuming continues from the saved epoch, keeping the earlier losses
    resumed = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg,
                             resume_state=states[0])
    assert len(resumed.losses) == 6 and resumed.losses[:3] == states[0]["losses"]
    assert np.abs(resumed.diffuse - res.diffuse).mean() < 0.05
    # saving and loading round-trips (8-bit PNG maps, float EXR env map)
    paths = save_appearance(res, tmp_path)
    for name in ("diffuse.png", "roughness.png", "metallic.png", "envmap.exr", "envmap.png", "appearance.json"):
        assert (tmp_path / "material" / name).is_file()
    back = load_appearance(tmp_path)
    assert np.allclose(back.envmap, res.envmap, atol=1e-5)
    assert np.abs(back.diffuse - res.diffuse).max() < 0.01
    assert np.abs(back.roughness - res.roughness).max() < 0.01
    assert back.config == res.config and paths["envmap"].suffix == ".exr"


def test_orbit_camera_keeps_distance_and_target(scene):
    cam = scene.camera
    centre = scene.vertices[0].mean(axis=0)
    cam45 = orbit_camera(cam, centre, 45.0)
    assert np.isclose(np.linalg.norm(cam45.center - centre), np.linalg.norm(cam.center - centre))
    # turned about the image-up axis (which is perpendicular to the viewing direction) by 45 degrees
    assert np.isclose(np.dot(cam45.forward, cam.forward), np.cos(np.radians(45.0)), atol=1e-9)
    assert np.allclose(cam45.up, cam.up, atol=1e-9)
    uv0, _ = cam.project(centre[None])
    uv1, _ = cam45.project(centre[None])
    assert np.allclose(uv0, uv1, atol=1e-6)  # the cloth centre stays at the same pixel
    cam45.validate()
