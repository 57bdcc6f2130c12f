"""The appearance scenes' motion (saft.synthetic.appearance.appearance_motion): start > 0 gives a curved frame 0;
motion "newton" gives Newton's cloth on a finer mesh, resampled to the template, scored on its own mesh."""

from __future__ import annotations

import numpy as np
import pytest

from saft.evaluate.appearance import true_geometry
from saft.scene import load_scene
from saft.scene.mesh import vertex_normals
from saft.synthetic.appearance import (AppearanceSceneSpec, appearance_motion, mark_run, newton_motion,
                                       run_is_current, scene_info, true_motion_on_template, write_appearance_scene)
from saft.synthetic.benchmark_scenes import DONE_FILE

TINY = AppearanceSceneSpec(grid=6, frames=3, frame_dt=0.04)


def test_start_drops_simulated_frames_and_makes_frame_zero_the_template():
    flat_template, flat, held = appearance_motion(TINY)
    np.testing.assert_allclose(flat[0], flat_template.vertices, atol=1e-12)     # frame 0 = the rest shape
    assert np.ptp(flat[0][:, 2]) < 1e-12                                         # a plane
    start = 12
    template, positions, held_s = appearance_motion(AppearanceSceneSpec(grid=6, frames=3, frame_dt=0.04, start=start))
    longer = appearance_motion(AppearanceSceneSpec(grid=6, frames=start + 3, frame_dt=0.04))[1]
    assert positions.shape == flat.shape
    np.testing.assert_allclose(positions, longer[start:], atol=1e-12)           # the same simulation, later
    np.testing.assert_allclose(template.vertices, positions[0], atol=1e-12)     # template = frame 0
    np.testing.assert_array_equal(template.quads, flat_template.quads)
    np.testing.assert_array_equal(held_s, held)
    # frame 0 is billowed: its normals spread, where the flat one's are all equal
    n = vertex_normals(template.vertices, template.triangles)
    assert np.degrees(np.arccos(np.clip(n @ n.mean(0) / np.linalg.norm(n.mean(0)), -1, 1))).max() > 5


def test_saft_motion_identity_is_the_one_written_before_motion_existed():
    info = scene_info(TINY)
    assert not {"motion", "gt_grid", "start", "self_contact"} & set(info["spec"]) and set(info) == {"kind", "spec"}
    newton = scene_info(AppearanceSceneSpec(grid=6, frames=3, motion="newton"))
    assert newton["spec"]["motion"] == "newton" and newton["spec"]["gt_grid"] == 40


def test_newton_identity_records_self_contact_so_the_clips_made_without_it_are_made_again():
    spec = AppearanceSceneSpec(grid=6, frames=3, motion="newton")
    info = scene_info(spec)
    assert info["spec"]["self_contact"] and info["newton"]["self_contact"] and info["newton"]["contact_margin"] > 0
    # the identity the clips were written with before (Newton without self-contact, recorded nowhere)
    before = {"kind": "appearance", "spec": {k: v for k, v in info["spec"].items() if k != "self_contact"}}
    assert info != before
    assert scene_info(AppearanceSceneSpec(grid=6, frames=3, motion="newton", self_contact=False)) != info


def test_a_cached_run_is_current_only_for_the_scene_it_was_made_of(tmp_path):
    scene, run = tmp_path / "scene", tmp_path / "run"
    scene.mkdir(), run.mkdir()
    (scene / DONE_FILE).write_text('{"spec": 1}')
    (run / "timings.json").write_text("{}")
    assert not run_is_current(run, scene, "timings.json")            # made before runs were marked
    mark_run(run, scene)
    assert run_is_current(run, scene, "timings.json") and not run_is_current(run, scene, "texture.png")
    (scene / DONE_FILE).write_text('{"spec": 2}')                     # the scene made again, from another spec
    assert not run_is_current(run, scene, "timings.json")


def test_newton_motion_is_the_fine_truth_and_its_resampling_to_the_template():
    pytest.importorskip("newton")  # the optional `bench` extra (install.sh --dev installs it)
    spec = AppearanceSceneSpec(grid=5, gt_grid=9, frames=3, motion="newton")
    template, on_template, held, truth_mesh, truth, frame_dt = newton_motion(spec)
    assert truth.shape == (3, 81, 3) and on_template.shape == (3, 25, 3)
    assert np.all(np.isfinite(truth)) and np.ptp(truth[2] - truth[0]) > 1e-4        # it moves
    # the template's material points are every other fine one: the resampling is exact there
    np.testing.assert_allclose(on_template, truth.reshape(3, 9, 9, 3)[:, ::2, ::2].reshape(3, 25, 3), atol=1e-12)
    np.testing.assert_allclose(template.vertices, on_template[0])
    np.testing.assert_allclose(truth_mesh.vertices, truth[0])
    assert template.quads.shape == (16, 4) and truth_mesh.quads.shape == (64, 4)
    np.testing.assert_array_equal(held, np.arange(5))                                # the top edge
    assert frame_dt == pytest.approx(1 / 30)
    np.testing.assert_array_equal(appearance_motion(spec)[1], on_template)


def test_newton_scene_scores_on_its_own_mesh(tmp_path):
    pytest.importorskip("newton")
    spec = AppearanceSceneSpec(fabric="satin", grid=5, gt_grid=9, frames=2, motion="newton", width=24, height=18,
                               spp=2, map_size=32, env_height=8, env_width=16)
    folder = write_appearance_scene(tmp_path / "scene", spec)
    scene = load_scene(folder)
    assert scene.template.num_vertices == 25 and scene.frame_dt == pytest.approx(1 / 30)
    verts, triangles, uvs = true_geometry(folder, scene.template)
    assert verts.shape == (2, 81, 3) and triangles.shape == (128, 3) and uvs.shape == (81, 2)
    assert true_motion_on_template(folder).shape == (2, 25, 3)
    rgb, mask = scene.frames.load()
    assert rgb.shape == (2, 18, 24, 3) and np.all(np.isfinite(rgb)) and mask.sum() > 0
    assert write_appearance_scene(tmp_path / "scene", spec) == folder                  # kept: same identity
