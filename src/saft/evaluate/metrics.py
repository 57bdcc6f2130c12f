"""Per-frame geometry metrics: Chamfer distances, point-to-surface distances and the depth error.

Definitions follow ``shared/data/phi_sft/README.md`` ("How the paper scores R1") and the supplementary
material of the SAFT paper, so that numbers compare with the published ones:

* The reconstructed triangle mesh is sampled with exactly as many points as the ground-truth (GT) cloud has:
  area-weighted triangle choice, uniform barycentric coordinates, from a seeded generator.
* ``CD2`` = mean over GT points of the squared distance to the nearest sample + mean over samples of the
  squared distance to the nearest GT point (the two directions are SUMMED). Reported in 1e-4 m².
* ``CD1``: the same with unsquared distances, reported in cm.
* ``p2s`` (one-sided, as the README defines it): distance from every GT point to the closest point of the
  reconstructed surface (exact point-to-triangle distance). L1 = mean distance (mm), L2 = mean squared
  distance (1e-4 m², the unit of CD2).
* ``p2s_sym`` (the paper's symmetric variant): p2s + the mean (L1) / mean squared (L2) distance from the
  mesh samples to the nearest GT point. The GT is a point cloud, so the mesh → GT direction is a distance to
  the nearest GT point (it equals the samples → GT term of the Chamfer distance).
* ``depth`` δ: mean |D_R − D_GT| over the pixels where both depth maps are valid, reported in cm.

Nearest neighbours come from ``scipy.spatial.cKDTree``; point-to-triangle distances from
``trimesh.triangles.closest_point`` on the candidate triangles that conservative bounds leave, so the
closest point is exact (see :func:`closest_points_on_mesh`).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

# Metric keys (the units are part of the names; they are also the keys of metrics.json).
CD2 = "cd2_1e-4m2"
CD1 = "cd1_cm"
P2S_L1 = "p2s_l1_mm"
P2S_L2 = "p2s_l2_1e-4m2"
P2S_SYM_L1 = "p2s_sym_l1_mm"
P2S_SYM_L2 = "p2s_sym_l2_1e-4m2"
DEPTH = "depth_cm"
NUM_POINTS = "num_gt_points"

METRIC_KEYS = (CD2, CD1, P2S_L1, P2S_L2, P2S_SYM_L1, P2S_SYM_L2)

# Scale factors from SI (m, m²) to the reported units.
_TO_1E4M2 = 1e4
_TO_CM = 1e2
_TO_MM = 1e3


def _as_triangles(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise ValueError("the mesh has no triangles")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ValueError("a triangle refers to a vertex that does not exist")
    return vertices[triangles]  # (T, 3, 3)


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, count: int,
                   rng: np.random.Generator) -> np.ndarray:
    """`count` points uniformly distributed on the triangle mesh: (count, 3) float64.

    Triangles are chosen with probability proportional to their area, then a point is drawn with uniform
    barycentric coordinates (the square-root warp of two uniforms, folded back into the triangle).
    """
    tris = _as_triangles(vertices, triangles)
    areas = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("the mesh has zero surface area (or non-finite vertices)")
    which = rng.choice(len(tris), size=int(count), p=areas / total)
    r = rng.random((int(count), 2))
    flip = r.sum(axis=1) > 1.0  # fold the unit square onto the lower triangle: uniform on the triangle
    r[flip] = 1.0 - r[flip]
    t = tris[which]
    return t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])


def _patches(centroids: np.ndarray, size: int) -> list[np.ndarray]:
    """Split triangle ids into spatially coherent groups of at most `size` (recursive median bisection)."""
    out, stack = [], [np.arange(len(centroids))]
    while stack:
        ids = stack.pop()
        if len(ids) <= size:
            out.append(ids)
            continue
        c = centroids[ids]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        order = ids[np.argsort(c[:, axis], kind="stable")]
        half = len(order) // 2
        stack += [order[:half], order[half:]]
    return out


def closest_points_on_mesh(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray,
                           patch_size: int = 32, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact closest point on a triangle mesh for every query point.

    Returns (closest (N, 3), distance (N,), triangle index (N,)).

    The point-to-triangle computation is ``trimesh.triangles.closest_point`` (Ericson's method); it is
    applied only to the triangles that can be the closest, found without any per-point Python loop:

    1. an upper bound u per point: the exact distance to the triangle whose centroid is nearest (cKDTree);
    2. triangles are grouped into patches of ``patch_size`` neighbours; each patch is enclosed in a slab
       (half-thickness t about its mean plane) intersected with a cylinder (radius R about the plane normal)
       so that dist(p, patch) ≥ sqrt(max(0, |h| − t)² + max(0, ρ − R)²), with h and ρ the normal and
       in-plane offsets of p from the patch centre; patches whose bound exceeds u are skipped;
    3. within the remaining patches the same bound per triangle (t = 0, R = centroid-to-corner radius)
       prunes again, and the survivors are measured exactly; the smallest distance wins.

    The bounds are true lower bounds, so the result is the exact minimum over all triangles (unlike
    ``trimesh.proximity.closest_point``, which can miss the closest face by ~10 µm and takes seconds per
    R1 frame when the surface is far from the points).
    """
    tris = _as_triangles(vertices, triangles)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)

    centroids = tris.mean(axis=1)
    radius = np.linalg.norm(tris - centroids[:, None, :], axis=2).max(axis=1)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unit = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)  # degenerate: 0

    groups = _patches(centroids, max(1, int(patch_size)))
    P, S = len(groups), max(len(g) for g in groups)
    table = np.full((P, S), -1, dtype=np.int64)
    p_centre, p_normal = np.zeros((P, 3)), np.zeros((P, 3))
    p_thick, p_radius = np.zeros(P), np.zeros(P)
    for i, g in enumerate(groups):  # once per patch (~60 for R1), not per point
        table[i, :len(g)] = g
        corners = tris[g].reshape(-1, 3)
        c = corners.mean(axis=0)
        nv = normals[g].sum(axis=0)
        ln = np.linalg.norm(nv)
        nv = nv / ln if ln > 0 else np.zeros(3)  # no mean plane: the bound falls back to a sphere
        dv = corners - c
        h = dv @ nv
        p_centre[i], p_normal[i] = c, nv
        p_thick[i] = np.abs(h).max()
        p_radius[i] = np.sqrt(np.maximum(np.einsum("ij,ij->i", dv, dv) - h * h, 0.0)).max()
    p_offset = np.einsum("ij,ij->i", p_centre, p_normal)
    p_sq = np.einsum("ij,ij->i", p_centre, p_centre)

    # 1. upper bound: the triangle with the nearest centroid
    _, best_t = cKDTree(centroids).query(pts, k=1, workers=-1)
    best_t = np.asarray(best_t, dtype=np.int64)
    best_c = trimesh.triangles.closest_point(tris[best_t], pts)
    best_d = np.linalg.norm(best_c - pts, axis=1)

    for s in range(0, n, chunk):
        p = pts[s:s + chunk]
        u = best_d[s:s + chunk]
        # 2. patch bounds; |p - c|² by expansion (GEMM): the 1e-6 m slack covers its rounding
        h = p @ p_normal.T - p_offset
        d2 = np.einsum("ij,ij->i", p, p)[:, None] - 2.0 * (p @ p_centre.T) + p_sq
        rho = np.sqrt(np.maximum(d2 - h * h, 0.0))
        lower2 = np.maximum(np.abs(h) - p_thick, 0.0) ** 2 + np.maximum(rho - p_radius, 0.0) ** 2
        r, q = np.nonzero(lower2 < ((u + 1e-6) ** 2)[:, None])
        rows = np.repeat(r, S)
        cand = table[q].reshape(-1)
        ok = cand >= 0
        rows, cand = rows[ok], cand[ok]
        # 3. triangle bounds, then exact distances for the survivors
        diff = p[rows] - centroids[cand]
        ht = np.einsum("ij,ij->i", diff, unit[cand])
        lat = np.maximum(np.sqrt(np.maximum(np.einsum("ij,ij->i", diff, diff) - ht * ht, 0.0)) - radius[cand], 0.0)
        keep = ht * ht + lat * lat < (u[rows] + 1e-9) ** 2
        rows, cand = rows[keep], cand[keep]
        if len(rows) == 0:
            continue
        cp = trimesh.triangles.closest_point(tris[cand], p[rows])
        dd = np.linalg.norm(cp - p[rows], axis=1)
        order = np.lexsort((dd, rows))  # by point, then by distance: the first of each point is its best
        rows, cand, cp, dd = rows[order], cand[order], cp[order], dd[order]
        first = np.ones(len(rows), dtype=bool)
        first[1:] = rows[1:] != rows[:-1]
        rf = rows[first]
        better = dd[first] < u[rf]
        sel = s + rf[better]
        best_d[sel] = dd[first][better]
        best_t[sel] = cand[first][better]
        best_c[sel] = cp[first][better]
    return best_c, best_d, best_t


def point_to_surface_distances(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance (m) from each point to the closest point of the triangle mesh surface: (N,)."""
    return closest_points_on_mesh(vertices, triangles, points)[1]


def nearest_neighbor_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """For each point of `source`, the distance to the nearest point of `target` (cKDTree, exact).

    The tree is built with compact_nodes=False, balanced_tree=False: when the clouds are centimetres
    apart (a bad reconstruction, the static-template baseline) queries are then 3–5× faster than with the
    defaults; the answer is the same.
    """
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    tree = cKDTree(target, compact_nodes=False, balanced_tree=False)
    return tree.query(source, k=1, workers=-1)[0]


def frame_rng(seed: int, frame_index: int) -> np.random.Generator:
    """The generator used for frame `frame_index`: numbers of a frame do not depend on the other frames."""
    return np.random.default_rng([int(seed), int(frame_index)])


def frame_metrics(vertices: np.ndarray, triangles: np.ndarray, gt_points: np.ndarray,
                  rng: np.random.Generator) -> dict[str, float]:
    """All point-cloud metrics of one frame (keys: METRIC_KEYS and NUM_POINTS), in the reported units.

    `vertices` (V, 3) and `gt_points` (N, 3) must be in the same frame, in metres.
    """
    gt = np.asarray(gt_points, dtype=np.float64).reshape(-1, 3)
    if len(gt) == 0:
        raise ValueError("the ground-truth point cloud is empty")
    samples = sample_surface(vertices, triangles, len(gt), rng)
    d_gt_to_samples = nearest_neighbor_distances(gt, samples)
    d_samples_to_gt = nearest_neighbor_distances(samples, gt)
    d_gt_to_surface = point_to_surface_distances(vertices, triangles, gt)

    cd2 = np.mean(d_gt_to_samples ** 2) + np.mean(d_samples_to_gt ** 2)
    cd1 = np.mean(d_gt_to_samples) + np.mean(d_samples_to_gt)
    p2s_l1 = np.mean(d_gt_to_surface)
    p2s_l2 = np.mean(d_gt_to_surface ** 2)
    return {
        CD2: float(cd2 * _TO_1E4M2),
        CD1: float(cd1 * _TO_CM),
        P2S_L1: float(p2s_l1 * _TO_MM),
        P2S_L2: float(p2s_l2 * _TO_1E4M2),
        P2S_SYM_L1: float((p2s_l1 + np.mean(d_samples_to_gt)) * _TO_MM),
        P2S_SYM_L2: float((p2s_l2 + np.mean(d_samples_to_gt ** 2)) * _TO_1E4M2),
        NUM_POINTS: int(len(gt)),
    }


def depth_error(depth_rendered: np.ndarray, depth_gt: np.ndarray, roi: np.ndarray | None = None) -> float:
    """δ of the paper: mean |D_R − D_GT| (metres in → metres out) over pixels valid in both maps.

    A pixel is valid where the depth is finite and > 0 (renderers and sensors write 0, NaN or inf where
    there is nothing). `roi` (bool, same shape) restricts the pixels further. NaN when no pixel is valid.
    Multiply by 100 for the reported unit (cm); :func:`depth_error_cm` does.
    """
    dr = np.asarray(depth_rendered, dtype=np.float64)
    dg = np.asarray(depth_gt, dtype=np.float64)
    dr = dr[..., 0] if dr.ndim == 3 and dr.shape[2] == 1 else dr
    dg = dg[..., 0] if dg.ndim == 3 and dg.shape[2] == 1 else dg
    if dr.shape != dg.shape or dr.ndim != 2:
        raise ValueError(f"depth maps must be two H×W arrays of one size, got {dr.shape} and {dg.shape}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(dr) & np.isfinite(dg) & (dr > 0) & (dg > 0)
    if roi is not None:
        roi = np.asarray(roi, dtype=bool)
        if roi.shape != dr.shape:
            raise ValueError(f"roi must have the depth maps' shape {dr.shape}, got {roi.shape}")
        valid &= roi
    if not valid.any():
        return float("nan")
    return float(np.mean(np.abs(dr[valid] - dg[valid])))


def depth_error_cm(depth_rendered: np.ndarray, depth_gt: np.ndarray, roi: np.ndarray | None = None) -> float:
    """:func:`depth_error` in cm (the paper's unit)."""
    return depth_error(depth_rendered, depth_gt, roi) * _TO_CM
