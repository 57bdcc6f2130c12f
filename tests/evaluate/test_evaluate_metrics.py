"""Metrics on hand-computed cases: p2s (interior, edge, vertex), Chamfer of a shifted sheet, sampling, depth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from saft.evaluate import (
    CD1, CD2, P2S_L1, P2S_L2, P2S_SYM_L1, P2S_SYM_L2, closest_points_on_mesh, depth_error, depth_error_cm,
    evaluate_sequence, frame_metrics, frame_rng, point_to_surface_distances, sample_surface,
)

TRI_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
TRI_F = np.array([[0, 1, 2]])


def grid_sheet(n: int, size: float, z: float = 0.0, wave: float = 0.0):
    """An n×n-vertex square sheet [0, size]² at height z (optionally wavy), triangulated."""
    u = np.linspace(0.0, size, n)
    x, y = np.meshgrid(u, u, indexing="xy")
    zz = z + wave * np.sin(2 * np.pi * x / size) * np.cos(3 * np.pi * y / size)
    v = np.stack([x.ravel(), y.ravel(), zz.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + 1, a + n + 1, a + n
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


@pytest.mark.parametrize(
    "point, expected_closest, case",
    [
        ([0.2, 0.2, 0.5], [0.2, 0.2, 0.0], "over the interior"),
        ([0.2, 0.2, -0.7], [0.2, 0.2, 0.0], "under the interior"),
        ([0.5, -0.3, 0.4], [0.5, 0.0, 0.0], "past edge AB"),
        ([1.0, 1.0, 0.0], [0.5, 0.5, 0.0], "past the hypotenuse"),
        ([-0.3, -0.4, 0.0], [0.0, 0.0, 0.0], "past vertex A"),
        ([1.3, -0.4, 1.2], [1.0, 0.0, 0.0], "past vertex B, above the plane"),
        ([-0.2, 1.5, 0.0], [0.0, 1.0, 0.0], "past vertex C"),
    ],
)
def test_p2s_hand_computed(point, expected_closest, case):
    closest, dist, tri = closest_points_on_mesh(TRI_V, TRI_F, np.array([point]))
    np.testing.assert_allclose(closest[0], expected_closest, atol=1e-12, err_msg=case)
    assert dist[0] == pytest.approx(np.linalg.norm(np.subtract(point, expected_closest)), abs=1e-12)
    assert tri[0] == 0


def test_p2s_picks_the_nearest_of_two_triangles():
    # A second triangle 0.3 above the first, shifted by (0.1, 0.1): (0.3, 0.3, 0.2) is over both interiors
    # and nearer the upper one; (0.05, 0.05, 0.2) is nearest the upper one's corner (0.1, 0.1, 0.3).
    v = np.concatenate([TRI_V, TRI_V + [0.1, 0.1, 0.3]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    d = point_to_surface_distances(v, f, np.array([[0.3, 0.3, 0.2], [0.3, 0.3, 0.1], [0.05, 0.05, 0.2]]))
    np.testing.assert_allclose(d, [0.1, 0.1, np.sqrt(0.05**2 + 0.05**2 + 0.1**2)], atol=1e-12)


def test_p2s_exact_against_brute_force_far_and_near():
    """The pruned search must equal the minimum over ALL triangles, near and far, for any patch size."""
    v, f = grid_sheet(12, 0.3, wave=0.03)
    rng = np.random.default_rng(1)
    pts = np.concatenate([
        rng.uniform([-0.05, -0.05, -0.05], [0.35, 0.35, 0.05], (300, 3)),   # near the sheet
        rng.uniform([-0.5, -0.5, -0.5], [0.8, 0.8, 0.5], (200, 3)),         # far, need more candidates
    ])
    tris = v[f]
    T = len(tris)
    cp = trimesh.triangles.closest_point(np.tile(tris, (len(pts), 1, 1)), np.repeat(pts, T, axis=0))
    brute = np.linalg.norm(cp - np.repeat(pts, T, axis=0), axis=1).reshape(-1, T).min(axis=1)
    for patch_size, chunk in [(32, 8192), (1, 7), (4, 100), (10_000, 64)]:
        closest, dist, tri = closest_points_on_mesh(v, f, pts, patch_size=patch_size, chunk=chunk)
        np.testing.assert_allclose(dist, brute, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(closest - pts, axis=1), dist, atol=1e-12)
        own = trimesh.triangles.closest_point(tris[tri], pts)  # the reported triangle gives that point
        np.testing.assert_allclose(own, closest, atol=1e-12)


def test_sample_surface_is_on_the_mesh_and_area_weighted():
    # Triangle 0 has area 0.5, triangle 1 (scaled by 3 in x) area 1.5: 1/4 of the samples on triangle 0.
    v = np.concatenate([TRI_V, TRI_V * [3.0, 1.0, 1.0] + [0.0, 0.0, 5.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    s = sample_surface(v, f, 40000, np.random.default_rng(0))
    assert s.shape == (40000, 3)
    frac0 = np.mean(s[:, 2] < 1.0)
    assert frac0 == pytest.approx(0.25, abs=0.01)
    assert point_to_surface_distances(v, f, s).max() < 1e-12
    # uniform on the triangle: the mean is the centroid
    np.testing.assert_allclose(s[s[:, 2] < 1.0].mean(axis=0), TRI_V.mean(axis=0), atol=0.01)


def test_flat_sheet_shifted_one_cm_along_its_normal():
    """GT on a sheet 1 cm above the mesh: every squared NN distance is (1 cm)² + an in-plane part.

    CD2 sums two directions, each ≥ (0.01 m)² = 1e-4 m²: CD2 = 2.0 (in 1e-4 m²) + the sampling floor.
    The in-plane floor of one direction is about area / (π N) (nearest neighbour of N uniform points).
    The p2s is exactly 1 cm for every GT point (they all lie over the sheet's interior).
    """
    size, n_pts = 0.1, 20000
    v, f = grid_sheet(6, size)
    gt = sample_surface(v, f, n_pts, np.random.default_rng(123)) + [0.0, 0.0, 0.01]
    m = frame_metrics(v, f, gt, frame_rng(0, 0))
    floor = 2 * size**2 / (math.pi * n_pts) * 1e4  # both directions, in 1e-4 m²
    assert 2.0 < m[CD2] < 2.0 + 3 * floor, (m[CD2], floor)
    assert 2.0 < m[CD1] < 2.0 + 0.01  # cm: each direction ≥ 1 cm, excess ≈ floor / (2 · 1 cm)
    assert m[P2S_L1] == pytest.approx(10.0, abs=1e-9)  # mm
    assert m[P2S_L2] == pytest.approx(1.0, abs=1e-9)  # 1e-4 m²
    assert 20.0 <= m[P2S_SYM_L1] < 20.1  # p2s + samples -> GT (≥ 1 cm each)
    assert 2.0 <= m[P2S_SYM_L2] < 2.0 + 3 * floor


def test_identical_clouds_give_only_the_sampling_floor():
    v, f = grid_sheet(6, 0.1)
    gt = sample_surface(v, f, 20000, np.random.default_rng(5))
    m = frame_metrics(v, f, gt, frame_rng(0, 0))
    assert 0.0 < m[CD2] < 3 * 2 * 0.1**2 / (math.pi * 20000) * 1e4
    assert m[P2S_L1] < 1e-9


def test_seeded_sampling_repeats_and_seed_matters():
    v, f = grid_sheet(6, 0.1, wave=0.01)
    gt = [sample_surface(v, f, 3000, np.random.default_rng(k)) + [0, 0, 0.002 * k] for k in range(3)]
    a = evaluate_sequence([v] * 3, f, gt, seed=7)
    b = evaluate_sequence([v] * 3, f, gt, seed=7)
    c = evaluate_sequence([v] * 3, f, gt, seed=8)
    assert a["per_frame"] == b["per_frame"] and a["mean"] == b["mean"]
    assert a["per_frame"][CD2] != c["per_frame"][CD2]
    assert a["per_frame"][P2S_L1] == c["per_frame"][P2S_L1]  # p2s does not sample
    # a frame's numbers do not depend on the other frames
    single = evaluate_sequence([v], f, gt[:1], seed=7)
    assert single["per_frame"][CD2][0] == a["per_frame"][CD2][0]
    assert a["mean"][CD2] == pytest.approx(np.mean(a["per_frame"][CD2]))


def test_evaluate_sequence_rejects_mismatched_lengths():
    v, f = grid_sheet(3, 0.1)
    with pytest.raises(ValueError, match="2 meshes but 1"):
        evaluate_sequence([v, v], f, [v])


def test_depth_error_over_pixels_valid_in_both():
    gt = np.array([[1.0, 1.0, 0.0], [np.nan, 2.0, 2.0]])
    rendered = np.array([[1.1, 0.0, 1.0], [1.0, 2.3, np.inf]])
    # valid in both: (0,0) |0.1| and (1,1) |0.3| -> mean 0.2 m
    assert depth_error(rendered, gt) == pytest.approx(0.2)
    assert depth_error_cm(rendered, gt) == pytest.approx(20.0)
    roi = np.zeros_like(gt, dtype=bool)
    roi[0, 0] = True
    assert depth_error(rendered, gt, roi) == pytest.approx(0.1)
    assert math.isnan(depth_error(np.zeros((2, 3)), gt))
    with pytest.raises(ValueError, match="one size"):
        depth_error(np.ones((2, 2)), gt)
    seq = evaluate_sequence([TRI_V], TRI_F, [TRI_V], depth_pairs=[(rendered, gt)])
    assert seq["per_frame"]["depth_cm"] == [pytest.approx(20.0)]


def test_p2s_exact_with_folds_and_degenerate_triangles():
    """A sheet folded back onto itself (opposite normals in one patch) plus zero-area triangles."""
    v, f = grid_sheet(6, 0.2, wave=0.02)
    folded = v * [1.0, 1.0, -1.0] + [0.0, 0.0, 0.05]
    degenerate_v = np.array([[0.1, 0.1, 0.3], [0.1, 0.1, 0.3], [0.2, 0.1, 0.3], [0.0, 0.0, -0.2]] * 1)
    verts = np.concatenate([v, folded, degenerate_v])
    nv = len(v)
    faces = np.concatenate([f, f[:, ::-1] + nv, [[2 * nv, 2 * nv + 1, 2 * nv + 2], [2 * nv + 3] * 3]])
    pts = np.random.default_rng(3).uniform([-0.1, -0.1, -0.3], [0.3, 0.3, 0.4], (400, 3))
    tris = verts[faces]
    T = len(tris)
    cp = trimesh.triangles.closest_point(np.tile(tris, (len(pts), 1, 1)), np.repeat(pts, T, axis=0))
    brute = np.linalg.norm(cp - np.repeat(pts, T, axis=0), axis=1).reshape(-1, T).min(axis=1)
    for patch_size in (32, 3):
        np.testing.assert_allclose(closest_points_on_mesh(verts, faces, pts, patch_size=patch_size)[1], brute,
                                   rtol=0, atol=1e-12)
