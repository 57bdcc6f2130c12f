"""Appearance metrics against ground truth: their invariances, their I/O and the texture-only baseline."""

import numpy as np
import pytest

from saft.evaluate.appearance import (AppearanceGroundTruth, beats, map_metrics, per_channel_scale,
                                      read_appearance_ground_truth, relit_metrics, texture_baseline, uv_coverage,
                                      write_appearance_ground_truth)
from saft.synthetic.appearance import grid_sheet, wave_motion
from saft.synthetic.fabrics import FABRICS, environment_map, fabric_maps
from saft.scene.camera import look_at


def _gt(kind="plaid", size=64):
    base, rough, metal = fabric_maps(kind, size)
    return AppearanceGroundTruth(base, rough, metal, environment_map("video", 16, 32),
                                 environment_map("unseen", 16, 32), {"max_depth": 2})


def test_fabrics_differ_and_lie_in_range():
    means = []
    for kind in FABRICS:
        base, rough, metal = fabric_maps(kind, 64)
        assert base.shape == (64, 64, 3) and rough.shape == metal.shape == (64, 64)
        assert 0 < base.min() and base.max() < 1 and 0 < rough.min() and rough.max() <= 1
        assert 0 <= metal.min() and metal.max() <= 1
        means.append((round(float(base.mean()), 3), round(float(rough.mean()), 3), round(float(metal.mean()), 3)))
    assert len(set(means)) == len(FABRICS)
    assert fabric_maps("lame", 64)[2].max() > 0.9 and fabric_maps("satin", 64)[1].min() < 0.3


def test_map_metrics_are_scale_invariant_in_diffuse_only():
    gt = _gt("lame")
    cover = np.ones(gt.roughness.shape, bool)
    exact = map_metrics(gt.base_color, gt.roughness, gt.metallic, gt, cover)
    scaled = map_metrics(gt.base_color * np.float32([0.5, 0.7, 2.0]), gt.roughness, gt.metallic, gt, cover)
    assert exact["diffuse_psnr_db"] > 80 and scaled["diffuse_psnr_db"] > 80
    assert np.allclose(scaled["diffuse_scale"], [2.0, 1 / 0.7, 0.5], rtol=1e-4)
    worse = map_metrics(gt.base_color.transpose(1, 0, 2), gt.roughness + 0.1, np.zeros_like(gt.metallic), gt, cover)
    assert worse["diffuse_psnr_db"] < 25
    assert worse["roughness_mae"] == pytest.approx(min(0.1, 1.0), abs=0.02)
    assert worse["metallic_mae"] == pytest.approx(gt.metallic.mean(), abs=1e-6)
    assert beats(exact, worse) == {"diffuse_psnr_db": True, "roughness_mae": True, "metallic_mae": True}


def test_per_channel_scale_is_least_squares():
    rng = np.random.default_rng(0)
    e = rng.random((8, 8, 3)).astype(np.float32)
    t = e * np.float32([1.5, 0.5, 3.0])
    assert np.allclose(per_channel_scale(e, t, np.ones((8, 8), bool)), [1.5, 0.5, 3.0], rtol=1e-5)


def test_uv_coverage_of_a_grid_sheet_is_the_whole_square():
    _, quads, uvs = grid_sheet(4)
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    assert uv_coverage(tri, uvs, 32).all()
    assert uv_coverage(tri[:len(quads)], uvs, 32).mean() == pytest.approx(0.5, abs=0.1)


def test_ground_truth_round_trip_and_baseline(tmp_path):
    gt = _gt("lame", 32)
    write_appearance_ground_truth(tmp_path / "appearance_gt", gt.base_color, gt.roughness, gt.metallic, gt.env_video,
                                  gt.env_unseen, {"max_depth": 2, "fabric": "lame"})
    back = read_appearance_ground_truth(tmp_path)
    assert back.info["fabric"] == "lame"
    assert np.abs(back.base_color - gt.base_color).max() < 0.01
    assert np.abs(back.metallic - gt.metallic).max() < 0.003
    assert np.allclose(back.env_unseen, gt.env_unseen)
    assert read_appearance_ground_truth(tmp_path / "nothing") is None
    d, r, m = texture_baseline(np.full((4, 4, 3), 0.5, np.float32))
    assert np.allclose(r, 1) and np.allclose(m, 0) and np.allclose(d, 0.214, atol=1e-3)


def test_relit_views_of_the_true_maps_match_and_wrong_maps_do_not():
    gt = _gt("satin", 32)
    verts0, quads, uvs = grid_sheet(4)
    verts = wave_motion(verts0, 3)
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    cam = look_at([0.3, 0.2, 1.8], [0, 0, 0], [0, 1, 0], K, 40, 30)
    same = relit_metrics(gt.base_color, gt.roughness, gt.metallic, gt, verts, tri, uvs, cam, spp=16)
    wrong = relit_metrics(gt.base_color[..., ::-1].copy(), np.ones_like(gt.roughness), gt.metallic, gt, verts, tri, uvs, cam,
                          spp=16)
    assert same["relit_video_psnr_db"] > 60 and same["relit_unseen_psnr_db"] > 60  # same seeds: identical
    assert wrong["relit_video_psnr_db"] < 30 and wrong["relit_unseen_psnr_db"] < 30


def test_result_folder_is_scored_beside_the_texture_only_baseline(tmp_path):
    """saft evaluate's appearance part: a result whose material/ holds the true maps beats its own
    phase-1 texture on every metric, and the metrics land in material/appearance.json."""
    import json

    import torch

    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import AppearanceResult, save_appearance
    from saft.appearance.params import linear_to_srgb
    from saft.evaluate.appearance_result import evaluate_appearance_result, format_appearance_table
    from saft.io_utils import write_image
    from saft.synthetic.appearance import AppearanceSceneSpec, write_appearance_scene

    spec = AppearanceSceneSpec(fabric="lame", frames=3, width=48, height=36, spp=8, map_size=64, grid=5,
                               env_height=16, env_width=32)
    scene = write_appearance_scene(tmp_path / "scene", spec)
    gt = read_appearance_ground_truth(scene)
    result = tmp_path / "result"
    shaded = linear_to_srgb(torch.as_tensor(gt.base_color * 0.6)).numpy()
    write_image(result / "texture.png", shaded)
    save_appearance(AppearanceResult(gt.base_color, gt.roughness, gt.metallic, gt.env_video, [], cpu_profile()), result)
    assert evaluate_appearance_result(result, tmp_path / "nothing") is None
    out = evaluate_appearance_result(result, scene, spp=8)
    assert all(out["phase3_better"].values()) and len(out["phase3_better"]) == 5
    saved = json.loads((result / "material" / "appearance.json").read_text())["ground_truth_metrics"]
    assert saved["phase3"]["roughness_mae"] < 0.01
    assert "texture only" in format_appearance_table(out)
