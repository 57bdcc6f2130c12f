"""The benchmark scenes (saft.synthetic.benchmark_scenes), made tiny: they load, start at the template and move."""

from __future__ import annotations

import numpy as np
import pytest

from saft.evaluate import ground_truth_spec_for, load_ground_truth_frames
from saft.io_utils import read_image
from saft.scene import load_scene
from saft.synthetic.benchmark_scenes import BenchSceneSpec, is_complete, scene_names, write_benchmark_scenes

TINY = BenchSceneSpec(grid=6, frames=4, frame_dt=0.06, image_size=48, spp=4, texture_size=64, gt_points=300)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench-scenes")
    write_benchmark_scenes(root, TINY)
    return root


@pytest.mark.parametrize("name", scene_names())
def test_scene_loads_starts_at_template_and_moves(scenes, name):
    scene = load_scene(scenes / name)
    assert scene.num_frames == TINY.frames and scene.frame_dt == TINY.frame_dt
    gt = np.load(scenes / name / "gt_vertices.npy")
    template = scene.template.vertices
    assert gt.shape == (TINY.frames, TINY.grid ** 2, 3)
    np.testing.assert_allclose(gt[0], template, atol=1e-6)  # frame 0 is the template, at rest
    motion = np.linalg.norm(gt[-1] - gt[0], axis=1).max()
    assert motion > 0.005, f"{name}: the cloth barely moves ({motion:.4f} m)"
    clouds = load_ground_truth_frames(ground_truth_spec_for(scene))
    assert len(clouds) == TINY.frames
    # the ground-truth cloud of frame 0 lies on the template (a flat or tilted square)
    nearest = np.linalg.norm(clouds[0][:, None] - template[None], axis=2).min(axis=1)
    assert nearest.max() < TINY.size / (TINY.grid - 1)
    mask = read_image(scenes / name / "mask" / "000.png")[..., 0]
    rgb = read_image(scenes / name / "rgb" / "000.png")
    inside, outside = rgb[mask > 0.5].mean(), rgb[mask < 0.5].mean()
    assert 0.05 < mask.mean() < 0.9 and inside > 0.05 and outside < 0.01  # a lit cloth on black
    if name.endswith("_pinned"):
        pins = scene.pinned
        assert pins is not None and len(pins) in (2, TINY.grid)
        np.testing.assert_allclose(gt[:, pins], np.broadcast_to(template[pins], gt[:, pins].shape), atol=1e-9)
    else:
        assert scene.pinned is None


def test_pinned_and_unpinned_share_the_video_and_cache_is_reused(scenes):
    for s in "abc":
        a, b = (read_image(scenes / f"{s}_{v}" / "rgb" / "003.png") for v in ("pinned", "unpinned"))
        np.testing.assert_array_equal(a, b)
    # scene c: the grabbed corner (bottom-left) is kinematic in the simulation but not a declared pin
    gt = np.load(scenes / "c_pinned" / "gt_vertices.npy")
    corner = (TINY.grid - 1) * TINY.grid
    assert corner not in load_scene(scenes / "c_pinned").pinned
    assert gt[-1, corner, 1] - gt[0, corner, 1] > 0.02 and gt[-1, corner, 2] > 0.02  # up and towards the camera
    assert all(is_complete(scenes / n, TINY) for n in scene_names())
    assert not is_complete(scenes / "a_pinned", BenchSceneSpec())
    stamp = (scenes / "a_pinned" / "generator.json").stat().st_mtime_ns
    write_benchmark_scenes(scenes, TINY)
    assert (scenes / "a_pinned" / "generator.json").stat().st_mtime_ns == stamp
