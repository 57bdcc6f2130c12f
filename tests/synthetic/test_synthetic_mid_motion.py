"""A scene without its first frames (saft.synthetic.mid_motion): a clip that starts mid-motion."""

import numpy as np
import pytest

from saft.scene import load_scene
from saft.scene.camera import look_at
from saft.scene.frames import FrameSequence
from saft.scene.scene import Scene
from saft.synthetic.benchmark_scenes import write_scene_folder
from saft.synthetic.hanging_cloth import grid_template
from saft.synthetic.mid_motion import template_at, write_mid_motion_scene


def test_template_at_resamples_a_finer_grid_and_keeps_the_same_one():
    fine = grid_template(5, 0.4).vertices
    np.testing.assert_allclose(template_at(fine, 3), grid_template(3, 0.4).vertices, atol=1e-12)
    assert template_at(fine, 5) is not None and np.array_equal(template_at(fine, 5), fine)
    with pytest.raises(ValueError):
        template_at(fine[:-1], 3)


def test_write_mid_motion_scene_drops_frames_and_starts_from_the_ground_truth(tmp_path):
    tpl = grid_template(3, 0.4)
    n = 5
    positions = np.stack([tpl.vertices + [0.0, 0.0, 0.01 * k] for k in range(n)])
    K = np.array([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]])
    camera = look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), K, 32, 24)
    rgb = np.stack([np.full((24, 32, 3), k / 10, dtype=np.float32) for k in range(n)])
    mask = np.ones((n, 24, 32), dtype=np.float32)
    scene = Scene(name="s", template=tpl, camera=camera, frames=FrameSequence((), None, 32, 24), pinned=np.array([0]),
                  frame_dt=0.1, gravity=np.array([0.0, -9.81, 0.0]))
    write_scene_folder(tmp_path / "s", scene, rgb, mask, [p.astype(np.float32) for p in positions], positions, {"x": 1})
    out = write_mid_motion_scene(tmp_path / "s", tmp_path / "mid" / "s", 2)
    mid = load_scene(out)
    assert len(mid.frames) == 3 and mid.frame_dt == 0.1 and list(mid.pinned) == [0]
    np.testing.assert_allclose(mid.template.vertices, positions[2], atol=1e-6)
    np.testing.assert_allclose(mid.frames.load([0])[0][0], rgb[2], atol=1 / 255)
    np.testing.assert_allclose(np.load(out / "gt" / "frame_000.npy"), positions[2], atol=1e-6)
    assert np.load(out / "gt_vertices.npy").shape == (3, 9, 3)
    with pytest.raises(ValueError):
        write_mid_motion_scene(tmp_path / "s", tmp_path / "bad", 4)
