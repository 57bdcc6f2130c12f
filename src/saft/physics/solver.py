"""Linear solvers for the implicit step A v = b, A = M + h^2 K (symmetric, 3V x 3V, fixed CSR pattern).

CPU (``ReusedLUSolver``, the default on CPU whatever else is installed): an incomplete sparse LU (SuperLU's
ILU via scipy, symmetric mode, minimum-degree ordering on A + A^T, drop tolerance 1e-3, float32) of some
recent A is kept and used as the preconditioner of conjugate gradients for the following solves. The
matrix drifts slowly from substep to substep, so CG converges in about twelve iterations; once it needs
more than ``refactor_after`` the next factorisation is of the current A. When CG fails (``max_iter``
reached, or a breakdown because A is indefinite) the current A is factorised afresh, then completely
(SuperLU) and solved directly (LU handles indefinite matrices). The adjoint solve of the backward pass
uses the same machinery with the factors kept from the forward pass.

The CG loop runs as one numba call (``pcg_numba.pcg``, backend "numba"): a mat-vec on A's upper 3x3
blocks (A must be symmetric: bit for bit with the projected Hessian, whose upper triangle the kernels
mirror; to 1e-16 relative with the exact one, far below any CG tolerance), fused vector updates, and as
preconditioner the symmetric M = P^T U^T D^-1 U P made from the factorisation's U alone
(SuperLU's ILU keeps about twice as many entries in L as in U; with U alone CG needs as many iterations
and an application costs a third). backend="scipy" is the reference: the same CG in numpy around
SuperLU's own triangular solves with L and U.

Why incomplete, and why 1e-3: CG's iteration count is set mostly by how far A has drifted since the
factorisation and hardly by the drop tolerance (R1 fwd+bwd, 392 solves: 4757 iterations at 1e-4, 4933 at
1e-3, 5091 at 3e-3), while the cost of an application follows the factor's size (U: 73k entries at 1e-4,
40k at 1e-3). Measured on benchmarks/bench_physics.py: see BENCHMARKS.md, "Physics rollout speed (issue 12)".
Everything here is single-threaded and deterministic: the same inputs give the same bits whatever the
torch thread count, and no decision depends on a timing or on which optional package is importable.

Any device (``JacobiCGSolver``, solver="cg"): Jacobi-preconditioned CG in torch on a sparse CSR tensor (the
CUDA path before ``solver_dense``, kept for comparison: ~245 iterations per solve on R1); on breakdown or
non-convergence it falls back to a dense solve (correct for indefinite A).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from saft.physics import pcg_numba as _pn
from saft.physics.factor_cache import FactorCache


def sparse_csr(crow, col, data, n):
    """The n × n torch sparse CSR matrix of the arrays (crow, col, data), built without its invariant check."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR is beta" / invariant-check notices
        return torch.sparse_csr_tensor(crow, col, data, size=(n, n), check_invariants=False)


class SolveStats:
    def __init__(self):
        self.solves = 0
        self.iterations = 0
        self.factorizations = 0
        self.fallbacks = 0
        self.extra: dict[str, int] = {}  # a solver's own counters (the dense solver's host reads)

    def as_dict(self):
        return dict(
            solves=self.solves, iterations=self.iterations, factorizations=self.factorizations,
            fallbacks=self.fallbacks, **self.extra,
        )


class ReusedLUSolver:
    """CPU: CG preconditioned by a reused sparse LU factorisation, refactorised when needed."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, tol: float = 1e-6, max_iter: int = 60,
                 refactor_after: int = 20, precond_float32: bool = True, stats: SolveStats | None = None,
                 keep_factors_bytes: int = 256 * 2**20, drop_tol: float = 1e-3, backend: str = "numba",
                 cache: FactorCache | None = None, step_offset: int = 0):
        self.indptr = indptr.astype(np.int32)
        self.indices = indices.astype(np.int32)
        if backend not in ("numba", "scipy"):
            raise ValueError(f"backend must be 'numba' or 'scipy', got {backend!r}")
        # "numba": the whole CG loop in one compiled call (pcg_numba); "scipy": the same algorithm in
        # numpy/scipy with SuperLU's triangular solves (the reference, for tests and comparisons)
        self.backend = backend
        self._uptr = indptr.astype(np.uint32)
        self._uidx = indices.astype(np.uint32)
        # the storage of A in the numba CG (pcg_numba._spmv): symmetric upper 3x3 blocks when the pattern has
        # saft's vertex-block layout (A is symmetric, values included), plain CSR otherwise
        self._sym = _pn.sym_blocks(self.indptr, self.indices) if _pn.is_blocked(indptr, indices) else None
        self.n = len(indptr) - 1
        self.tol = tol
        self.max_iter = max_iter
        self.refactor_after = refactor_after  # CG needed more iterations: refresh the factor for next time
        self.precond_float32 = precond_float32
        self.drop_tol = drop_tol  # ILU drop tolerance; 0: complete LU preconditioner
        self.lu = None
        self.lu_f32 = False
        self.pre = None  # the factor's triangles as pcg_numba arrays (None: pivoted LU, or scipy backend)
        self.incomplete = False  # the current factor is an ILU (not usable for a direct solve)
        self.stats = stats if stats is not None else SolveStats()
        # factors made during the forward pass, by substep: the adjoint solve of substep i (same matrix
        # A_i) is preconditioned by the factor made nearest to i instead of a stale or fresh one
        self.step = None
        self.adjoint_mode = False
        self.keep_factors_bytes = keep_factors_bytes
        self.factors: dict[int, tuple] = {}
        self._factor_bytes = 0
        # a FactorCache shared with earlier rollouts (factor_cache.py): the kept factors live there, keyed by
        # absolute substep (this rollout's substep i is step_offset + i), and every solve, the forward's too,
        # starts from the nearest of them
        self.cache = cache
        self.step_offset = step_offset
        if cache is not None:
            self.factors = cache.entries

    def at_step(self, i: int | None, select: bool = False):
        """Tag the following solves with substep ``i``; with ``select`` switch to the kept factor made
        nearest to it (the backward pass walks the substeps in reverse)."""
        self.step = i
        # the adjoint pass reuses kept factors and refactorises only when CG fails
        self.adjoint_mode = select
        if (select or self.cache is not None) and self.factors and i is not None:
            at = i + self.step_offset
            j = min(self.factors, key=lambda k: abs(k - at))
            self.lu, self.lu_f32, self.pre = self.factors[j]

    def _keep(self):
        if self.step is None:
            return
        if self.cache is not None:
            self._keep_in_cache()
            return
        nbytes = self._factor_nbytes(self.lu, self.lu_f32, self.pre)
        if self._factor_bytes + nbytes > self.keep_factors_bytes:
            # over budget: thin out the kept factors (every other one), keeping the spread over time
            for k in sorted(self.factors)[1::2]:
                entry = self.factors.pop(k)
                self._factor_bytes -= self._factor_nbytes(*entry)
            if self._factor_bytes + nbytes > self.keep_factors_bytes:
                return
        self.factors[self.step] = (self.lu, self.lu_f32, self.pre)
        self._factor_bytes += nbytes

    def _keep_in_cache(self):
        """Keep the fresh factor under its absolute substep (replacing an older one there); only the arrays
        of the numba CG, so that the cache can be checkpointed (factor_cache.py)."""
        cache = self.cache
        if self.pre is None:
            return
        key = self.step + self.step_offset
        nbytes = cache.entry_nbytes(self.pre)
        if key in cache.entries:
            cache.nbytes -= cache.entry_nbytes(cache.entries.pop(key)[2])
        if cache.nbytes + nbytes > cache.budget_bytes:
            for k in sorted(cache.entries)[1::2]:  # over budget: thin out, keeping the spread over time
                cache.nbytes -= cache.entry_nbytes(cache.entries.pop(k)[2])
            if cache.nbytes + nbytes > cache.budget_bytes:
                return
        cache.entries[key] = (None, self.lu_f32, self.pre)
        cache.nbytes += nbytes

    def _factor_nbytes(self, lu, f32, pre=None):
        extra = 0 if pre is None else sum(a.nbytes for a in pre)
        return lu.nnz * (4 + (4 if f32 else 8)) + extra

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n), copy=False)

    def factorize(self, data: np.ndarray, pivoting: bool = False, complete: bool = False):
        # the pattern and the values are symmetric, so the CSR arrays are also a valid CSC of A
        # the preconditioner is factorised in float32 (half the memory traffic in the triangular
        # solves); CG itself runs in float64, so the solution accuracy is unaffected
        self.lu_f32 = self.precond_float32 and not pivoting
        fdata = data.astype(np.float32) if self.lu_f32 else data
        A = sp.csc_matrix((fdata, self.indices, self.indptr), shape=(self.n, self.n), copy=False)
        # symmetric mode, diagonal pivots only: ~15x less fill than partial pivoting on this pattern
        self.incomplete = not (pivoting or complete) and self.drop_tol > 0
        if pivoting:
            self.lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A")
        elif self.incomplete:
            self.lu = spla.spilu(A, drop_tol=self.drop_tol, fill_factor=10.0, permc_spec="MMD_AT_PLUS_A",
                                 diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
        else:
            self.lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options=dict(SymmetricMode=True))
        # the triangles for the numba CG (symmetric permutations only: not the pivoted LU, which is only
        # used for direct solves)
        self.pre = None
        if self.backend == "numba" and not pivoting:
            try:
                self.pre = _pn.factors_from_superlu(self.lu, self.lu_f32)
            except ValueError:  # a zero pivot: CG around SuperLU's own solves (then the usual fallbacks)
                self.pre = None
        self.stats.factorizations += 1
        self._keep()

    def solve(self, data: np.ndarray, b: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        self.stats.solves += 1
        bnorm = float(np.linalg.norm(b))
        if bnorm == 0.0:
            return np.zeros_like(b)
        atol = self.tol * bnorm
        if self.lu is not None or self.pre is not None:  # (a cached factor has only the numba CG's arrays)
            x, its = self._pcg(data, b, x0, atol)
            if x is not None:
                if its > self._refactor_threshold():
                    # also in the adjoint pass: kept under this substep, the new factor is then the nearest
                    # one for the following (earlier) substeps
                    self.factorize(data)
                return x
            self.stats.fallbacks += 1
        self.factorize(data)
        x, its = self._pcg(data, b, x0, atol)  # with the fresh factor: a few iterations
        if x is not None:
            return x
        if self.incomplete:  # a direct solve needs the complete factor
            self.factorize(data, complete=True)
            x, its = self._pcg(data, b, x0, atol)
            if x is not None:
                return x
        A = self.matrix(data)
        x = self._solve_lu(b)
        for _ in range(4):  # iterative refinement
            r = b - A @ x
            if np.linalg.norm(r) <= atol:
                return x
            x += self._solve_lu(r)
        if not np.linalg.norm(b - A @ x) <= atol:
            # diagonal pivoting failed (strongly indefinite A): partial pivoting, float64, more fill
            self.factorize(data, pivoting=True)
            x = self._solve_lu(b)
            for _ in range(4):
                r = b - A @ x
                if np.linalg.norm(r) <= atol:
                    break
                x += self._solve_lu(r)
        return x

    def _refactor_threshold(self) -> int:
        # A fixed iteration count, never a measured time: decisions that depend on timings would make
        # rollouts (and so whole reconstructions) differ from run to run. 20: on R1 CG settles at ~12
        # iterations however old the ILU is (a fresh one still needs ~5), and a refactorisation (~17 ms) costs
        # about 220 iterations of the numba CG (78 us), so it pays only when the matrix has drifted well
        # beyond that. R1, 50 frames, fwd+bwd, iterations / factorisations / cost at 78 us + 17 ms each, for
        # thresholds 15 -> 20: benchmark forcing (a_vert 0.5) 4933 / 7 / 505 ms -> 5612 / 1 / 455 ms;
        # twice stronger 4579 / 30 / 867 ms -> 5978 / 12 / 670 ms; a_vert 0.1: 3199 / 1 either way.
        return self.refactor_after

    def _solve_lu(self, r):
        return self.lu.solve(r.astype(np.float32) if self.lu_f32 else r).astype(np.float64)

    def _pcg(self, data, b, x0, atol):
        """CG from x0 preconditioned by the current factor: (x, iterations), x None on failure."""
        if self.pre is None:
            return self._pcg_reference(self.matrix(data), b, x0, atol)
        x = np.zeros(self.n) if x0 is None else np.array(x0, dtype=np.float64)
        data = np.ascontiguousarray(data, dtype=np.float64)
        if self._sym is not None:
            bptr, bcol, src = self._sym
            mat = (bptr, bcol, _pn.gather(data, src), 2)
        else:
            mat = (self._uptr, self._uidx, data, 0)
        status, its = _pn.pcg(*mat, np.ascontiguousarray(b, dtype=np.float64), x, float(atol), self.max_iter,
                              *self.pre)
        self.stats.iterations += its
        return (x if status == 0 else None), its

    def _pcg_reference(self, A, b, x0, atol):
        lu = self
        x = np.zeros_like(b) if x0 is None else x0.copy()
        r = b - A @ x
        rn = float(np.linalg.norm(r))
        if rn <= atol:
            return x, 0
        z = lu._solve_lu(r)
        p = z.copy()
        rz = float(r @ z)
        for it in range(self.max_iter):
            if not rz > 0.0:
                return None, it
            Ap = A @ p
            pAp = float(p @ Ap)
            if not pAp > 0.0:
                return None, it
            alpha = rz / pAp
            x += alpha * p
            r -= alpha * Ap
            self.stats.iterations += 1
            if float(np.linalg.norm(r)) <= atol:
                return x, it + 1
            z = lu._solve_lu(r)
            rz_new = float(r @ z)
            # flexible (Polak-Ribiere) beta = z_new . (r_new - r_old) / rz: robust to the slightly
            # unsymmetric ILU preconditioner; r_new - r_old = -alpha Ap, so it costs one dot product
            p *= -alpha * float(z @ Ap) / rz
            p += z
            rz = rz_new
        return None, self.max_iter


try:  # optional: CHOLMOD through scikit-sparse (needs the SuiteSparse library)
    from sksparse.cholmod import CholmodError as _CholmodError
    from sksparse.cholmod import analyze as _cholmod_analyze

    HAVE_CHOLMOD = True
except Exception:  # noqa: BLE001 - not installed or the shared library is missing
    HAVE_CHOLMOD = False

_CHOLMOD_SYMBOLIC: dict = {}  # pattern key -> analysed Factor (fill-reducing ordering + etree), once per topology


class CholmodPCGSolver(ReusedLUSolver):
    """CPU, when scikit-sparse (CHOLMOD) is importable: the same reused-factor PCG as ``ReusedLUSolver``
    with a sparse Cholesky factor instead of the SuperLU one. The symbolic analysis (ordering, elimination
    tree) is done once per sparsity pattern and cached; each refactorisation is numeric only. On the R1
    system (3072 DOFs) the simplicial LL^T factor has ~half the entries of the symmetric-mode LU, so a
    preconditioner application costs ~0.27 ms instead of ~0.6 ms and a refactorisation ~23 ms. The factor
    is float64. A non-SPD matrix ("exact" Hessian under compression) falls back to SuperLU with pivoting.
    """

    def __init__(self, indptr, indices, **kw):
        kw.setdefault("backend", "scipy")  # CG in numpy around CHOLMOD's solves (pre stays None)
        kw.setdefault("refactor_after", 15)  # its own cost ratio (factorisation ~85 iterations), as before
        super().__init__(indptr, indices, **kw)
        self.precond_float32 = False
        key = (self.n, len(self.indices), hash(self.indptr.tobytes()), hash(self.indices.tobytes()))
        self._key = key
        self._nnz_l = None

    def _symbolic(self, A):
        ent = _CHOLMOD_SYMBOLIC.get(self._key)
        if ent is None:
            F = _cholmod_analyze(A, mode="simplicial", ordering_method="best")
            ent = _CHOLMOD_SYMBOLIC[self._key] = [F, None]
        return ent

    def _factor_nbytes(self, lu, f32, pre=None):
        if isinstance(lu, spla.SuperLU):
            return super()._factor_nbytes(lu, f32, pre)
        return self._nnz_l * 12

    def factorize(self, data: np.ndarray, pivoting: bool = False):
        if pivoting:
            return super().factorize(data, pivoting=True)
        A = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n), copy=False)
        ent = self._symbolic(A)
        try:
            F = ent[0].cholesky(A)
        except _CholmodError:
            return super().factorize(data, pivoting=True)  # not positive definite: pivoted LU
        if ent[1] is None:
            ent[1] = F.L().nnz
        self._nnz_l = ent[1]
        self.lu, self.lu_f32, self.pre = F, False, None
        self.stats.factorizations += 1
        self._keep()

    def _solve_lu(self, r):
        if isinstance(self.lu, spla.SuperLU):
            return super()._solve_lu(r)
        return self.lu(r)


class JacobiCGSolver:
    """Device-agnostic torch CG with a Jacobi preconditioner on a sparse CSR matrix."""

    def __init__(self, crow: torch.Tensor, col: torch.Tensor, diag_idx: torch.Tensor, tol: float = 1e-10,
                 max_iter: int = 2000, stats: SolveStats | None = None):
        self.crow, self.col, self.diag_idx = crow, col, diag_idx
        self.n = crow.numel() - 1
        self.tol = tol
        self.max_iter = max_iter
        self.stats = stats if stats is not None else SolveStats()

    def matrix(self, data: torch.Tensor):
        return sparse_csr(self.crow, self.col, data, self.n)

    def solve(self, data: torch.Tensor, b: torch.Tensor, x0: torch.Tensor | None = None) -> torch.Tensor:
        self.stats.solves += 1
        A = self.matrix(data)
        bnorm = torch.linalg.vector_norm(b)
        atol = self.tol * bnorm
        dinv = 1.0 / data[self.diag_idx]
        x = torch.zeros_like(b) if x0 is None else x0.clone()
        r = b - A @ x
        z = dinv * r
        p = z.clone()
        rz = torch.dot(r, z)
        ok = False
        check_every = 10
        for it in range(1, self.max_iter + 1):
            Ap = A @ p
            pAp = torch.dot(p, Ap)
            alpha = rz / pAp
            x = x + alpha * p
            r = r - alpha * Ap
            z = dinv * r
            rz_new = torch.dot(r, z)
            p = z + (rz_new / rz) * p
            rz = rz_new
            if it % check_every == 0:
                rn = torch.linalg.vector_norm(r)
                if bool(rn <= atol) or bnorm == 0:
                    ok = True
                    break
                if not bool(torch.isfinite(rn)) or not bool(pAp > 0):
                    break
        self.stats.iterations += it
        if ok:
            return x
        # breakdown (indefinite A) or no convergence: dense solve, exact for any non-singular A
        self.stats.fallbacks += 1
        return torch.linalg.solve(A.to_dense(), b)
