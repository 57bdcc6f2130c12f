"""The independent-simulator scenes (saft.synthetic.independent_scenes, newton_cloth): the aerodynamics, the
grids, the model-matched twin, and (where the optional `bench` extra is installed) Newton's cloth, made tiny."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

import saft.synthetic.independent_scenes as independent_scenes
from saft.scene import load_scene
from saft.synthetic.appearance import AppearanceSceneSpec, _newton_gust, newton_motion
from saft.synthetic.benchmark_scenes import DONE_FILE
from saft.synthetic.hanging_cloth import grid_template
from saft.synthetic.independent_scenes import (SCENARIOS, IndependentSceneSpec, grid_indices, is_complete,
                                               resample_grid, meshes, scenario, simulate_independent,
                                               scene_names, simulate_matched, split_name, write_scenario)
from saft.synthetic.newton_cloth import AIR_DENSITY, NewtonClothParams, aero_forces

TRI = np.array([[0, 1, 2]])
FLAT = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # area 0.5, normal +z


def test_wind_along_the_normal_pushes_with_the_dynamic_pressure():
    p = NewtonClothParams(drag_normal=1.3, drag_tangent=0.0)
    f = aero_forces(FLAT, np.zeros((3, 3)), TRI, np.array([[0.0, 0.0, 2.0]]), p)
    np.testing.assert_allclose(f.sum(axis=0), [0.0, 0.0, 0.5 * AIR_DENSITY * 1.3 * 0.5 * 4.0])
    np.testing.assert_allclose(f[0], f[1])  # spread evenly over the three vertices
    # a cloth moving through still air feels the same force, opposed to its motion (air drag)
    g = aero_forces(FLAT, np.tile([0.0, 0.0, -2.0], (3, 1)), TRI, np.zeros((1, 3)), p)
    np.testing.assert_allclose(g, f)
    # the sign of the normal does not matter: wind from the other side pushes the other way
    h = aero_forces(FLAT, np.zeros((3, 3)), TRI[:, ::-1], np.array([[0.0, 0.0, -2.0]]), p)
    np.testing.assert_allclose(h, -f)


def test_wind_along_the_cloth_only_rubs():
    p = NewtonClothParams(drag_normal=1.0, drag_tangent=0.05)
    f = aero_forces(FLAT, np.zeros((3, 3)), TRI, np.array([[3.0, 0.0, 0.0]]), p)
    np.testing.assert_allclose(f.sum(axis=0), [0.05 * 0.5 * 3.0, 0.0, 0.0])


def test_grids_indices_and_names():
    field = np.stack(np.meshgrid(np.linspace(0, 1, 7), np.linspace(0, 2, 7), indexing="ij"), -1)
    out = resample_grid(field, 4)  # a linear field is resampled exactly
    np.testing.assert_allclose(out[5], [1 / 3, 2 / 3])
    assert list(grid_indices([(0.0, 0.0), (0.0, 1.0)], 5)) == [0, 4]
    assert list(grid_indices([(0.0, 0.0)], 5, clip=0.25)) == [0, 1, 5]  # the diagonal neighbour is 0.35 away
    for name in scene_names():
        scen, sim, variant = split_name(name)
        assert f"{scen}_{sim}_{variant}" == name
    with pytest.raises(ValueError):
        split_name("gust_pinned")


def test_both_meshes_share_the_rest_shape_and_the_held_corners():
    spec = IndependentSceneSpec(gt_grid=9, grid=5)
    gt, tpl = meshes(scenario("corners", spec), spec)
    assert gt.vertices.shape == (81, 3) and tpl.vertices.shape == (25, 3)
    np.testing.assert_allclose(gt.vertices[[0, 8, 72, 80]], tpl.vertices[[0, 4, 20, 24]], atol=1e-12)
    assert gt.vertices[:, 2].max() > 0.1  # tilted towards the camera
    np.testing.assert_allclose(meshes(scenario("gust", spec), spec)[1].vertices, grid_template(5, spec.size).vertices,
                               atol=1e-12)


def test_the_matched_twin_holds_its_pins_and_follows_the_felt_wind():
    spec = IndependentSceneSpec(gt_grid=7, grid=5, frames=5)
    sc = scenario("gust", spec)
    gt, tpl = meshes(sc, spec)
    still = np.repeat(gt.vertices[None], spec.frames, axis=0)  # a ground truth that does not move
    x = simulate_matched(sc, gt, tpl, still, spec)
    assert x.shape == (5, 25, 3)
    np.testing.assert_allclose(x[:, :5], np.broadcast_to(tpl.vertices[:5], (5, 5, 3)), atol=1e-12)  # top row held
    assert x[-1, 20:, 2].mean() > 1e-4  # the breeze from behind pushes the hem towards the camera (+z)


def _newton_params(monkeypatch, call) -> list:
    """The NewtonClothParams that `call()` hands to Newton (Newton itself replaced by a cloth that does not move)."""
    seen = []

    def fake(vertices, triangles, num_frames, frame_dt, params, **kw):
        seen.append(params)
        return np.repeat(np.asarray(vertices)[None], num_frames, axis=0)
    monkeypatch.setattr(independent_scenes, "simulate_newton_cloth", fake)
    _newton_gust.cache_clear()    # the appearance clips keep the last gust: neither reuse nor keep the fake one
    try:
        call()
    finally:
        _newton_gust.cache_clear()
    return seen


def test_every_scenario_is_simulated_with_newtons_self_contact(monkeypatch):
    # without it the one corner's, the flag's, both gusts' and the corners' truths pass through themselves
    # (diagnose_self_contact.py: 5 to 23 of 32 frames); only the fold had it
    spec = IndependentSceneSpec(gt_grid=7, grid=5, frames=2)
    for name in SCENARIOS:
        sc = scenario(name, spec)
        (params,) = _newton_params(monkeypatch, lambda: simulate_independent(sc, meshes(sc, spec)[0], spec))
        assert params.self_contact and params.contact_margin > 0, name


def test_a_scene_made_without_self_contact_is_regenerated(tmp_path):
    spec = IndependentSceneSpec()
    old = replace(spec, newton=replace(spec.newton, self_contact=False))  # the benchmark's scenes before the change
    for name, made in (("old", old), ("new", spec)):
        (tmp_path / name).mkdir()
        (tmp_path / name / DONE_FILE).write_text(json.dumps({"spec": independent_scenes._spec_json(made)}))
    assert not is_complete(tmp_path / "old", spec) and is_complete(tmp_path / "new", spec)


def test_the_appearance_clips_simulate_newtons_gust_with_self_contact(monkeypatch):
    # without it their truth's hem crease passed through the cloth in frames 13-20
    spec = AppearanceSceneSpec(motion="newton", gt_grid=7, grid=5, frames=2)
    (params,) = _newton_params(monkeypatch, lambda: newton_motion(spec))
    assert params.self_contact and params == IndependentSceneSpec().newton    # the shape benchmark's Newton
    (params,) = _newton_params(monkeypatch, lambda: newton_motion(replace(spec, self_contact=False)))
    assert not params.self_contact


def test_newton_cloth_hangs_from_its_pins_and_billows():
    pytest.importorskip("newton")
    from saft.synthetic.newton_cloth import simulate_newton_cloth

    mesh = grid_template(6, 0.3)
    wind = lambda p, t: np.tile([0.0, 0.0, 2.0], (len(p), 1))  # noqa: E731
    x = simulate_newton_cloth(mesh.vertices, mesh.triangles, 4, 1 / 30, NewtonClothParams(substeps=5),
                              kinematic=np.arange(6), wind=wind)
    assert x.shape == (4, 36, 3) and np.isfinite(x).all()
    np.testing.assert_allclose(x[:, :6], np.broadcast_to(mesh.vertices[:6], (4, 6, 3)), atol=1e-6)
    assert x[-1, 30:, 2].mean() > 0.005  # the hem billows along the wind
    calm = simulate_newton_cloth(mesh.vertices, mesh.triangles, 4, 1 / 30, NewtonClothParams(substeps=5),
                                 kinematic=np.arange(6))
    assert abs(calm[-1, :, 2]).max() < 1e-6 and calm[-1, 30:, 1].mean() < mesh.vertices[30:, 1].mean() - 1e-4


def test_write_scenario_tiny(tmp_path):
    pytest.importorskip("newton")
    spec = IndependentSceneSpec(gt_grid=8, grid=5, frames=3, width=48, height=36, spp=4, texture_size=64,
                                gt_points=200, newton=NewtonClothParams(substeps=4, iterations=4, self_contact=True))
    folders = write_scenario(tmp_path, "fold", spec)
    assert sorted(f.name for f in folders) == sorted(scene_names(("fold",)))
    ind, mat = load_scene(tmp_path / "fold_independent_pinned"), load_scene(tmp_path / "fold_matched_unpinned")
    assert ind.num_frames == 3 and ind.template.vertices.shape == (25, 3) and list(ind.pinned) == list(range(5))
    assert mat.pinned is None and mat.frame_dt == pytest.approx(1 / 30)
    assert np.load(tmp_path / "fold_independent_pinned" / "gt_vertices.npy").shape == (3, 64, 3)
    assert np.load(tmp_path / "fold_matched_pinned" / "gt_vertices.npy").shape == (3, 25, 3)
