import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import cube_mesh, grid_mesh  # noqa: E402

from saft.physics import ClothTopology  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"
R1 = SHARED / "data" / "phi_sft" / "data" / "R1" / "0_R1_quad.obj"


def _pattern_matrix(t, data):
    n = 3 * t.num_vertices
    return sp.csr_matrix((data, t.csr_indices, t.csr_indptr), shape=(n, n))


def test_grid_counts_classification_and_mass():
    n = 4
    v, q = grid_mesh(n, size=0.1)
    t = ClothTopology.from_quads(v, q, density=0.1)
    V = (n + 1) ** 2
    assert t.num_vertices == V
    assert t.num_springs == 2 * n * (n + 1)
    # hinges: sum over vertices of C(valence, 2)
    val = np.zeros(V, int)
    for a, b in t.edges.numpy():
        val[a] += 1
        val[b] += 1
    assert t.num_hinges == int((val * (val - 1) // 2).sum())
    # straight pairs (bending): per row/column line of n+1 vertices there are n-1 interior vertices
    assert int(t.is_bend.sum()) == 2 * (n + 1) * (n - 1)
    theta0 = t.rest_angle.numpy()
    assert np.allclose(theta0[t.is_bend.numpy()], math.acos(0.99))
    assert np.allclose(theta0[~t.is_bend.numpy()], math.pi / 2)
    assert np.allclose(t.rest_len.numpy(), 0.1 / n)
    assert t.mass.sum().item() == pytest.approx(0.1 * 0.1 * 0.1)
    # corner vertex: one quad, triangles (a,b,c),(a,c,d): corner 0 is 'a' of both -> 2 * (A/2)/3
    quad_area = (0.1 / n) ** 2
    assert t.mass[0].item() == pytest.approx(0.1 * quad_area / 3)


def test_irregular_closed_mesh_and_pattern():
    v, q = cube_mesh()
    t = ClothTopology.from_quads(v, q)
    assert t.num_springs == 12
    assert t.num_hinges == 8 * 3  # valence 3 everywhere
    assert not bool(t.is_bend.any())  # all neighbour pairs at 90 deg -> shearing
    # pattern: symmetric, sorted columns, contains every element entry
    n = 24
    A = _pattern_matrix(t, np.ones(t.nnz))
    assert (A != A.T).nnz == 0
    assert A.has_sorted_indices
    for idx in (t.spring_idx, t.hinge_idx, t.diag_idx):
        assert int(idx.max()) < t.nnz and int(idx.min()) >= 0
    rows = np.repeat(np.arange(n), np.diff(t.csr_indptr))
    d = t.diag_idx.numpy()
    assert np.array_equal(rows[d], t.csr_indices[d]) and np.array_equal(rows[d], np.arange(n))


def test_to_dtype_device_roundtrip():
    v, q = grid_mesh(2)
    t = ClothTopology.from_quads(v, q).to(dtype=torch.float32)
    assert t.mass.dtype == torch.float32 and t.edges.dtype == torch.int64
    assert t.to(dtype=torch.float64).template.dtype == torch.float64


def test_rejects_bad_indices():
    v, q = grid_mesh(2)
    with pytest.raises(ValueError):
        ClothTopology.from_quads(v, q + 100)


@pytest.mark.skipif(not R1.is_file(), reason=f"R1 template not found at {R1} (needs ../shared)")
def test_r1_template():
    from saft.scene.mesh import read_obj

    m = read_obj(R1)
    t = ClothTopology.from_mesh(m)
    assert t.num_vertices == 1024
    assert t.num_springs == 2 * 32 * 31
    assert np.array_equal(np.sort(t.edges.numpy(), axis=0), np.sort(m.edges, axis=0))
    assert float(t.mass.min()) > 0
    # most hinges of a gently curved grid are either bending or shearing, both present
    assert 0 < int(t.is_bend.sum()) < t.num_hinges
