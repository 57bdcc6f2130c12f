"""The numba CG of the CPU solver (saft.physics.pcg_numba) against scipy/SuperLU references."""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import grid_mesh, grid_system  # noqa: E402

from saft.physics import ClothTopology, PhysicsParams, rollout  # noqa: E402
from saft.physics import pcg_numba as P  # noqa: E402
from saft.physics.solver import ReusedLUSolver  # noqa: E402




def _superlu(Am, drop_tol, f32=False):
    A = sp.csc_matrix(Am.astype(np.float32 if f32 else np.float64))
    kw = dict(permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    if drop_tol:
        return spla.spilu(A, drop_tol=drop_tol, fill_factor=10.0, **kw)
    return spla.splu(A, **kw)


def test_superlu_factors_reproduce_lu_solve():
    """How SuperLU's factors relate to A (no scaling): Pr A Pc = L U with Pr = Pc^T in symmetric mode, so
    x = Pc U^-1 L^-1 Pr b reproduces lu.solve (complete and incomplete factors)."""
    _, _, b, Am = grid_system()
    n = Am.shape[0]
    for drop_tol in (0.0, 1e-3):
        lu = _superlu(Am, drop_tol)
        assert np.array_equal(lu.perm_r, lu.perm_c)
        Pr = sp.csc_matrix((np.ones(n), (lu.perm_r, np.arange(n))), shape=(n, n))
        Pc = sp.csc_matrix((np.ones(n), (np.arange(n), lu.perm_c)), shape=(n, n))
        y = spla.spsolve_triangular(lu.L.tocsr(), Pr @ b, lower=True)
        x = Pc @ spla.spsolve_triangular(lu.U.tocsr(), y, lower=False)
        ref = lu.solve(b)
        assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()
        if not drop_tol:
            assert abs(Pr @ Am @ Pc - lu.L @ lu.U).max() <= 1e-12 * abs(Am).max()


def test_precond_of_complete_factor_is_lu_solve():
    """From a complete factorisation the symmetric U-only preconditioner is A^-1: it matches lu.solve
    (float64 factor: to rounding; float32 factor: to float32 rounding)."""
    _, _, b, Am = grid_system()
    for f32, tol in ((False, 1e-9), (True, 1e-4)):
        lu = _superlu(Am, 0.0, f32=f32)
        z = P.precond_apply(*P.factors_from_superlu(lu, f32=f32), b)
        ref = lu.solve(b.astype(np.float32) if f32 else b).astype(np.float64)
        assert np.abs(z - ref).max() <= tol * np.abs(ref).max()
        assert np.abs(Am @ z - b).max() <= 10 * tol * np.abs(b).max()


def test_precond_of_incomplete_factor_is_symmetric_u_factorisation():
    """From an ILU the preconditioner is M = P^T U^T D^-1 U P (U: SuperLU's incomplete U, P: its
    permutation), built here explicitly with scipy."""
    _, _, b, Am = grid_system()
    n = Am.shape[0]
    lu = _superlu(Am, 1e-3, f32=True)
    U = sp.csc_matrix(lu.U).astype(np.float64)
    Pm = sp.csc_matrix((np.ones(n), (lu.perm_r, np.arange(n))), shape=(n, n))  # P r: y[perm[i]] = r[i]
    M = Pm.T @ U.T @ sp.diags(1.0 / U.diagonal()) @ U @ Pm
    z = P.precond_apply(*P.factors_from_superlu(lu), b)
    assert np.abs(M @ z - b).max() <= 1e-5 * np.abs(b).max()  # float32 values of U1
    assert abs(M - M.T).max() <= 1e-12 * abs(M).max()


@pytest.mark.parametrize("mode", ["projected", "exact"])
def test_system_matrix_is_symmetric(mode):
    """The numba CG multiplies by A's upper blocks only, so A must be symmetric: bit for bit with the
    projected Hessian (the kernels mirror the upper triangle), to rounding (1e-16 relative, far below any
    CG tolerance) with the exact one."""
    _, _, _, Am = grid_system(mode, compress=0.97)
    asym = abs(Am - Am.T).max()
    assert asym == 0.0 if mode == "projected" else asym <= 1e-14 * abs(Am).max()


def test_matvec_storages_match_scipy():
    """CSR and symmetric upper-block products agree with scipy; the solver uses the latter where the
    pattern has the vertex-block layout."""
    t, A, _, Am = grid_system()
    assert P.is_blocked(t.csr_indptr, t.csr_indices)
    ptr, idx = t.csr_indptr.astype(np.uint32), t.csr_indices.astype(np.uint32)
    bptr, bcol, src = P.sym_blocks(t.csr_indptr, t.csr_indices)
    assert len(src) == 9 * len(bcol) and 2 * len(src) - 9 * t.num_vertices == len(A)
    v = np.random.default_rng(1).standard_normal(Am.shape[0])
    out = np.empty_like(v)
    for mode, mat in ((0, (ptr, idx, A)), (2, (bptr, bcol, P.gather(A, src)))):
        P._spmv(*mat, mode, v, out)
        assert np.abs(out - Am @ v).max() <= 1e-13 * np.abs(Am @ v).max()
    s = ReusedLUSolver(t.csr_indptr, t.csr_indices)
    assert s._sym is not None
    # patterns without the vertex-block layout use the generic product
    r = sp.random(9, 9, density=0.4, format="csr", random_state=0)
    assert not P.is_blocked(r.indptr, r.indices)
    idx2 = t.csr_indices.copy()
    idx2[[3, 4]] = idx2[[4, 3]]
    assert not P.is_blocked(t.csr_indptr, idx2)


@pytest.mark.parametrize("drop_tol", [1e-3, 1e-4, 0.0])
def test_numba_pcg_matches_scipy_reference(drop_tol):
    """Both backends of ReusedLUSolver, preconditioned by the factor of a drifted matrix, reach the direct
    solution; the numba one (U-only preconditioner) needs no more iterations than the reference (L and U)
    and gives the same bits on every call."""
    t, A0, _, _ = grid_system()
    _, A, b, Am = grid_system(drift=2e-4)
    ref = spla.spsolve(Am.tocsc(), b)
    its, xs = {}, {}
    for backend in ("numba", "scipy"):
        def solve():
            s = ReusedLUSolver(t.csr_indptr, t.csr_indices, tol=1e-12, drop_tol=drop_tol, backend=backend)
            s.factorize(A0)
            return s, s.solve(A, b, np.zeros_like(b))

        s, x = solve()
        assert np.abs(x - ref).max() <= 1e-9 * np.abs(ref).max()
        assert s.stats.fallbacks == 0
        its[backend], xs[backend] = s.stats.iterations, x
        if backend == "numba":
            assert all(np.array_equal(x, solve()[1]) for _ in range(2))
    assert its["numba"] <= its["scipy"] + max(2, 0.2 * its["scipy"]), its  # not more iterations
    assert np.abs(xs["numba"] - xs["scipy"]).max() <= 1e-9 * np.abs(ref).max()


def test_numba_pcg_tolerance_and_start():
    """pcg stops at ||b - A x|| <= atol (checked independently), starts from the given x and reports
    iterations; a zero residual start returns at once."""
    t, A0, _, _ = grid_system()
    _, A, b, Am = grid_system(drift=1e-4)
    lu = _superlu(sp.csr_matrix((A0, t.csr_indices, t.csr_indptr)), 1e-3, f32=True)
    pre = P.factors_from_superlu(lu)
    ptr, idx = t.csr_indptr.astype(np.uint32), t.csr_indices.astype(np.uint32)
    for tol in (1e-4, 1e-8, 1e-12):
        x = np.zeros_like(b)
        atol = tol * np.linalg.norm(b)
        status, its = P.pcg(ptr, idx, A, 0, b, x, atol, 200, *pre)
        assert status == 0 and 0 < its < 200
        assert np.linalg.norm(b - Am @ x) <= atol * (1 + 1e-6)
    status, its = P.pcg(ptr, idx, A, 0, Am @ x, x.copy(), 1e-12, 200, *pre)
    assert status == 0 and its <= 1


def test_numba_pcg_breaks_down_on_indefinite_matrix_and_solver_falls_back():
    """The exact Hessian under compression makes A indefinite: the numba CG reports a breakdown, and the
    solver still returns the solution (fallback to complete then pivoted factorisations)."""
    t, A, b, Am = grid_system("exact", compress=0.97)
    assert np.linalg.eigvalsh(Am.toarray()).min() < 0
    lu = _superlu(Am, 0.0)  # complete, diagonal pivots: D has negative entries
    ptr, idx = t.csr_indptr.astype(np.uint32), t.csr_indices.astype(np.uint32)
    x = np.zeros_like(b)
    status, its = P.pcg(ptr, idx, A, 0, b, x, 1e-10 * np.linalg.norm(b), 60, *P.factors_from_superlu(lu))
    assert status in (0, 1)  # M = A^-1 exactly may converge at once; otherwise a breakdown, never max_iter
    s = ReusedLUSolver(t.csr_indptr, t.csr_indices, tol=1e-10)
    s.factorize(sp.csr_matrix(grid_system("projected")[3]).data)  # an SPD factor: CG must fail on this A
    x = s.solve(A, b)
    assert s.stats.fallbacks == 1
    assert np.linalg.norm(Am @ x - b) <= 1e-10 * np.linalg.norm(b)


def test_default_tolerance_accuracy_against_tight_solves():
    """The default solver tolerance (1e-6) stays close to tol 1e-12 solves: positions to 1e-7 m and
    gradients to 5e-3 relative (R1, 12 frames: 2.6e-8 and <= 8.2e-4; see BENCHMARKS.md)."""
    v, q = grid_mesh(10, wave=0.02)
    t = ClothTopology.from_quads(v, q)
    F = 8
    g = torch.Generator().manual_seed(3)
    p = PhysicsParams.default(F, t.num_vertices)
    p.a_vert = 0.5 * torch.randn(F - 1, t.num_vertices, 3, generator=g, dtype=torch.float64)
    W = torch.randn(F, t.num_vertices, 3, generator=g, dtype=torch.float64)
    out = {}
    for tol in (1e-6, 1e-12):
        pp = PhysicsParams(*(x.detach().clone().requires_grad_(True) for x in p.tensors()))
        pos = rollout(t, t.template, None, pp, num_frames=F, tol=tol)
        (pos * W).sum().backward()
        out[tol] = (pos.detach(), [x.grad for x in pp.tensors() if x.grad is not None])
    assert (out[1e-6][0] - out[1e-12][0]).abs().max() <= 1e-7
    for a, b in zip(out[1e-6][1], out[1e-12][1]):
        assert (a - b).abs().max() <= 5e-3 * b.abs().max()
