"""Small meshes shared by the physics tests (imported by path; tests dirs have no __init__.py)."""

from __future__ import annotations

import numpy as np


def grid_mesh(n: int, size: float = 0.1, wave: float = 0.0, plane: str = "xz"):
    """(n+1)^2 vertices, n^2 quads; optional sinusoidal wave out of the plane."""
    xs = np.linspace(0.0, size, n + 1)
    A, B = np.meshgrid(xs, xs, indexing="ij")
    a, b = A.ravel(), B.ravel()
    off = wave * np.sin(20.0 * a)
    if plane == "xz":
        verts = np.stack([a, off, b], axis=1)
    else:  # "xy": hanging sheet, row 0 at the top (y = 0), rows going down
        verts = np.stack([b, -a, off], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
    return verts, quads


def cube_mesh(size: float = 0.1):
    """Closed quad mesh with 8 valence-3 (irregular) vertices."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float) * size
    quads = np.array(
        [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]], dtype=np.int64
    )
    return v, quads


def grid_system(mode: str = "projected", compress: float = 1.0, drift: float = 0.0, n: int = 12):
    """A system matrix A = M + h^2 K of an n x n grid (CSR data; ``drift``: metres of random motion added to
    the same perturbed state, as between substeps), its topology, a right-hand side and A as scipy CSR."""
    import scipy.sparse as sp
    import torch

    from saft.physics import ClothTopology, ElementEval

    v, q = grid_mesh(n, wave=0.02)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(0)
    x = compress * t.template + 0.002 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    x = x + drift * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    A = ElementEval(t, x, 200.0, 1e-3, 1e-4, mode).system_values(0.005**2, t.mass.repeat_interleave(3)).numpy()
    N = 3 * t.num_vertices
    b = np.random.default_rng(0).standard_normal(N)
    return t, A, b, sp.csr_matrix((A, t.csr_indices, t.csr_indptr), shape=(N, N))
