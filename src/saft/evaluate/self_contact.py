"""Self-contact measures of a cloth mesh sequence: layers touching, the surface passing through itself.

A cloth without self-contact (saft's model, or Newton's without it) may let a flap pass through the cloth;
these count it on meshes with a flat rest grid (benchmarks/diagnose_self_contact.py uses them per frame).
"Non-neighbours" are vertices further apart than a given distance on the rest (material) cloth: at that
distance only a fold brings them close. Vertex-to-vertex distances depend on the sampling: a layer lying
on the cloth is as far from the nearest vertex of the other as half a grid spacing aside; the triangle
crossings are exact.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from saft.scene.mesh import vertex_normals


def far_pairs(rest: np.ndarray, pos: np.ndarray, distance: float, rest_min: float) -> np.ndarray:
    """(P, 2) vertex pairs closer than `distance` in `pos` and further than `rest_min` apart in `rest`."""
    pairs = cKDTree(pos).query_pairs(distance, output_type="ndarray")
    if len(pairs) == 0:
        return pairs.reshape(0, 2)
    keep = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1) > rest_min
    return pairs[keep]


def layered(rest: np.ndarray, pos: np.ndarray, distance: float, rest_min: float) -> np.ndarray:
    """(V,) bool: the vertex has a non-neighbour (further than rest_min at rest) within `distance` in `pos`."""
    out = np.zeros(len(pos), dtype=bool)
    out[far_pairs(rest, pos, distance, rest_min).ravel()] = True
    return out


def min_gap(rest: np.ndarray, pos: np.ndarray, rest_min: float, reach: float = 0.05) -> float:
    """Smallest 3-D distance (m) between vertices further than `rest_min` apart at rest (`reach` if none closer)."""
    pairs = far_pairs(rest, pos, reach, rest_min)
    return float(np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1).min()) if len(pairs) else reach


def crossing_triangles(pos: np.ndarray, tri: np.ndarray) -> int:
    """Number of triangle pairs sharing no vertex in which an edge of one crosses the other (in float64: on float32
    positions the edge-plane determinants of a flat, tilted sheet are rounding noise above the 1e-14 cut, and
    hundreds of coplanar neighbours "cross")."""
    pos = np.asarray(pos, dtype=np.float64)
    edges = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)
    e0, e1 = pos[edges[:, 0]], pos[edges[:, 1]]
    a, b, c = pos[tri[:, 0]], pos[tri[:, 1]], pos[tri[:, 2]]
    cen = (a + b + c) / 3
    reach = np.linalg.norm(e1 - e0, axis=1).max() / 2 + np.linalg.norm(pos[tri] - cen[:, None], axis=2).max()
    cand = cKDTree((e0 + e1) / 2).query_ball_tree(cKDTree(cen), reach)
    ei = np.repeat(np.arange(len(edges)), [len(c_) for c_ in cand])
    ti = np.concatenate([np.asarray(c_, dtype=np.int64) for c_ in cand]) if len(ei) else np.zeros(0, np.int64)
    shared = (tri[ti] == edges[ei, 0:1]).any(1) | (tri[ti] == edges[ei, 1:2]).any(1)
    ei, ti = ei[~shared], ti[~shared]
    # Möller–Trumbore, segment e0 + s (e1 - e0), s in [0, 1]
    d = e1[ei] - e0[ei]
    u1, u2 = b[ti] - a[ti], c[ti] - a[ti]
    p = np.cross(d, u2)
    det = (u1 * p).sum(1)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s0 = e0[ei] - a[ti]
    u = (s0 * p).sum(1) * inv
    q = np.cross(s0, u1)
    v = (d * q).sum(1) * inv
    s = (u2 * q).sum(1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)
    # the triangles holding each crossing edge, paired with the crossed triangle (sharing no vertex)
    out = set()
    for e, t in zip(ei[hit], ti[hit]):
        for t2 in np.flatnonzero((tri == edges[e, 0]).any(1) & (tri == edges[e, 1]).any(1)):
            if not np.isin(tri[t2], tri[t]).any():
                out.add((min(t, t2), max(t, t2)))
    return len(out)


def side(pos: np.ndarray, tri: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Per pair (i, j): sign of (x_i - x_j) · n_j and of (x_j - x_i) · n_i, 0 where within 1 mm of the plane."""
    n = vertex_normals(pos, tri)
    d = pos[pairs[:, 0]] - pos[pairs[:, 1]]
    sj, si = (d * n[pairs[:, 1]]).sum(1), (-d * n[pairs[:, 0]]).sum(1)
    return np.stack([np.where(np.abs(sj) > 1e-3, np.sign(sj), 0), np.where(np.abs(si) > 1e-3, np.sign(si), 0)], 1)
