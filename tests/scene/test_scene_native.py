import json
import shutil

import numpy as np
import pytest

from saft.errors import SaftInputError
from saft.scene import load_scene
from saft.scene.camera import Crop
from saft.scene.native import write_native_scene


def test_reads_every_part(native_scene):
    s = load_scene(native_scene)
    assert s.template.num_vertices == 16 and s.template.quads.shape == (9, 4)
    assert s.template.triangles.shape == (18, 3)
    assert s.camera.width == 40 and s.camera.fx == 40
    assert s.num_frames == 3
    f = s.frames[1]
    assert f.rgb.shape == (32, 40, 3) and f.mask.shape == (32, 40)
    assert f.rgb.dtype == np.float32 and abs(f.rgb[10, 20, 0] - 140 / 255) < 1e-6
    assert f.mask.sum() == 16 * 16
    assert s.frame_dt == pytest.approx(0.04)
    assert list(s.pinned) == [12, 13, 14, 15]
    assert np.allclose(s.gravity, [0, 9.81, 0])


def test_quad_edges_and_uvs(native_scene):
    s = load_scene(native_scene)
    assert len(s.template.edges) == 2 * 3 * 4  # 4x4 grid: 12 horizontal + 12 vertical
    assert np.allclose(s.template.uvs[5], [1 / 3, 1 / 3])


def test_no_masks_are_derived_from_non_black_pixels(native_scene, caplog):
    shutil.rmtree(native_scene / "mask")
    s = load_scene(native_scene)
    with caplog.at_level("WARNING", logger="saft"):
        m0, m1 = s.frames[0].mask, s.frames[1].mask
    assert m0.sum() == 16 * 16 and m1.sum() == 16 * 16
    assert sum("deriving" in r.message for r in caplog.records) == 1


def test_default_gravity_is_opposite_camera_up(native_scene):
    (native_scene / "scene.json").write_text("{}")
    s = load_scene(native_scene)
    # OpenCV camera with identity pose: image-up is world -y, so gravity points along +y.
    assert np.allclose(s.gravity_or_default(), [0, 9.81, 0])
    assert s.frame_dt == pytest.approx(0.02)


def test_fx_fy_cx_cy_form(native_scene):
    cam = json.loads((native_scene / "camera.json").read_text())
    del cam["K"]
    cam.update(fx=40, fy=41, cx=19.5, cy=15.5)
    (native_scene / "camera.json").write_text(json.dumps(cam))
    assert load_scene(native_scene).camera.fy == 41


def test_crop_and_scale_view(native_scene):
    meta = json.loads((native_scene / "scene.json").read_text())
    meta["crop"] = {"top": 4, "left": 8, "height": 24, "width": 24}
    (native_scene / "scene.json").write_text(json.dumps(meta))
    s = load_scene(native_scene)
    assert s.crop == Crop(4, 8, 24, 24)
    frames, cam = s.working_frames(), s.working_camera()
    assert frames[0].rgb.shape == (24, 24, 3) and (cam.width, cam.height) == (24, 24)
    uv_full, _ = s.camera.project(s.template.vertices)
    uv_crop, _ = cam.project(s.template.vertices)
    assert np.allclose(uv_crop, uv_full - [8, 4])
    half = s.working_frames(0.5)[0]
    assert half.rgb.shape == (12, 12, 3)
    cam_half = s.working_camera(0.5)
    assert np.allclose(cam_half.project(s.template.vertices)[0], (uv_crop + 0.5) * 0.5 - 0.5)


def test_write_then_read_round_trip(native_scene, tmp_path):
    s = load_scene(native_scene)
    rgb, mask = s.frames.load()
    pts = [s.template.vertices + [0, 0, 0.01 * i] for i in range(3)]
    out = write_native_scene(tmp_path / "copy", s, rgb, mask, ground_truth=pts)
    s2 = load_scene(out)
    assert np.allclose(s2.template.vertices, s.template.vertices, atol=1e-6)
    assert np.allclose(s2.camera.K, s.camera.K) and s2.frame_dt == pytest.approx(s.frame_dt)
    assert np.allclose(s2.frames[2].rgb, s.frames[2].rgb, atol=1 / 255)
    assert s2.ground_truth_dir is not None and s2.ground_truth_frame == "world"


def test_scene_not_found(tmp_path):
    with pytest.raises(SaftInputError, match="not found"):
        load_scene(tmp_path / "nothing")


def test_template_noise_is_seeded_tiny_and_leaves_the_rest(native_scene):
    s = load_scene(native_scene)
    a, b, c = s.with_template_noise(1), s.with_template_noise(1), s.with_template_noise(2)
    assert np.array_equal(a.template.vertices, b.template.vertices)
    moved = a.template.vertices - s.template.vertices
    assert 0 < np.abs(moved).max() < 1e-8
    assert not np.array_equal(a.template.vertices, c.template.vertices)
    assert np.array_equal(a.template.triangles, s.template.triangles) and a.frames == s.frames
