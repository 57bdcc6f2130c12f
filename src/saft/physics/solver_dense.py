"""CG preconditioned by a reused dense factor, in torch on any device (the CUDA default).

The same scheme as ``solver.ReusedLUSolver`` (the CPU default), with pieces that suit a GPU: a dense
Cholesky factor (cuSOLVER potrf through ``torch.linalg.cholesky_ex``) of some recent A = M + h^2 K is kept
and used as the preconditioner of float64 CG for the following solves; once CG needs more than
``refactor_after`` iterations the current A is factorised, and when CG fails (``max_iter``, or a breakdown
because A is indefinite) it is factorised afresh, and when that fails too (not positive definite) A is solved
directly by a dense LU with partial pivoting and iterative refinement. The convergence test is the CPU's:
||b - A x|| <= tol ||b||. The adjoint pass of the backward reuses the factors kept from the forward pass,
the one made nearest to each substep (``at_step``), as on the CPU.

Preconditioners (``precond``):
  "inv32"  the factor's explicit inverse (cholesky_inverse), stored in float32 and applied as one GEMV
           (37.7 MB read on R1's 3072 unknowns: ~10 us of HBM time; a triangular solve pair is a long
           chain of small dependent kernels on a GPU). CG itself stays float64, with the CPU's flexible
           (Polak-Ribiere) beta. Inverse: ~2/3 n^3 flops more than the factor, once per factorisation.
  "inv64"  the same in float64.
  "invbf16" the same in bfloat16 (18.9 MB on R1: half the GEMV's memory traffic, float32's range, 3 digits;
           CG stays float64, so only the iteration count can change).
  "chol"   the Cholesky factor itself, applied by cholesky_solve (two triangular solves).
``factor32``: factorise (Cholesky and inverse) in float32 instead of float64 (a fresh float64 factorisation
where the float32 one fails): the inverse preconditioners only ("inv32", "invbf16"), which are rounded to
float32 or bfloat16 anyway; CG stays float64.
``refactor_every_solve``: factorise every A (a direct solve; CG then converges in one or two iterations).
``refactor_age``: also factorise when the current factor was made more than that many substeps away. Off by
default (the CPU's rule alone); R1 on the CPU, 50 frames fwd+bwd, 392 solves: 5231 CG iterations and 1
factorisation without, 4668 / 4 at 50, 4115 / 8 at 25, 3431 / 16 at 12, 2798 / 28 at 6 (the forward's factors
serve the adjoint too), so it pays on a GPU when a factorisation costs less than ~100-150 iterations.

A mat-vec with A uses the fixed pattern as ELLPACK (rows padded to the longest, padding pointing at a zero
value): a gather, a product and a row sum, the same three kernels whatever the row lengths, deterministic
(no atomics), and the same code on the CPU. CG runs in blocks of ``block`` iterations whose steps become
zero once the residual is small enough, so the host reads the state (one sync) only between blocks; the
first read comes after as many iterations as the previous solve needed (after one block with a fresh
factor). On CUDA the set-up of a solve and a block are each recorded once as a CUDA graph (``cuda_graphs``;
with ``compile`` torch.compile fuses them first); the buffers and graphs belong to a workspace shared by the
solvers of one pattern (one rollout after another).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch
from torch.profiler import record_function

from saft.physics.cuda_graphs import Graphed, graphs_wanted
from saft.physics.solver import SolveStats

PRECONDS = ("inv32", "inv64", "invbf16", "chol")
_PRECOND_DTYPE = {"inv32": torch.float32, "invbf16": torch.bfloat16}  # else float64
_TINY = 1e-300  # clamps CG's denominators: 0 / 0 (a zero residual) gives 0


def ell_pattern(indptr: np.ndarray, indices: np.ndarray):
    """(src, col), both (n, w): the CSR pattern as ELLPACK. src[i, j] is the position in the CSR data of
    row i's j-th entry (nnz, one past the end, for padding), col[i, j] its column (0 for padding)."""
    indptr = np.asarray(indptr, dtype=np.int64)
    n, nnz = len(indptr) - 1, int(indptr[-1])
    lens = np.diff(indptr)
    w = max(int(lens.max()) if n else 0, 1)
    rows = np.repeat(np.arange(n), lens)
    pos = np.arange(nnz) - np.repeat(indptr[:-1], lens)
    src = np.full((n, w), nnz, dtype=np.int64)
    col = np.zeros((n, w), dtype=np.int64)
    src[rows, pos] = np.arange(nnz)
    col[rows, pos] = np.asarray(indices, dtype=np.int64)
    return src, col


class _Work:
    """The static buffers of one pattern on one device, and the set-up and CG-block functions on them
    (recorded as CUDA graphs on CUDA). ``owner``: the number of the factor loaded as the preconditioner.

    The block is written for few kernels per iteration (each is a launch, or a graph node of a few us, on a
    GPU). Once ||r|| <= tol ||b|| the step length is multiplied by 0, so the iterations left in a block change
    nothing (iterating on past convergence underflows to 0 / 0 within a few iterations of a fresh factor),
    and ``its`` counts the iterations begun above the tolerance (what the CPU counts). The denominators are
    clamped at 1e-300 so that an exactly zero residual (b = 0) stays zero. A breakdown (p.Ap <= 0 or
    r.z <= 0: A or the factor not positive definite) blows up or stalls the residual, which the host reads as
    a failure. No ``out=`` arguments, no views of the state, scalars as 1-element arrays: torch.compile
    (functionalisation) lost updates of 0-dim tensors and of values read through views of ``out=`` results.
    """

    def __init__(self, indptr, indices, device, precond: str, block: int, graphs: bool, compile: bool):
        f = dict(device=device, dtype=torch.float64)
        n, nnz = len(indptr) - 1, int(indptr[-1])
        self.n, self.nnz, self.block, self.precond = n, nnz, block, precond
        src, col = ell_pattern(indptr, indices)
        self.src = torch.as_tensor(src, device=device)
        self.col = torch.as_tensor(col, device=device)
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(np.asarray(indptr, dtype=np.int64)))
        self.flat = torch.as_tensor(rows * n + np.asarray(indices, dtype=np.int64), device=device)
        self.data = torch.zeros(nnz + 1, **f)  # A's CSR values and one zero for the ELL padding
        self.vals = torch.zeros(src.shape, **f)
        self.dense = torch.zeros(n, n, **f)  # A for a factorisation or the direct solve
        self.b, self.x, self.r, self.p = (torch.zeros(n, **f) for _ in range(4))
        # the scalars as 1-element arrays: torch.compile turned 0-dim CPU tensors into constants
        self.rz, self.rr, self.atol2, self.tol2, self.its = (torch.zeros(1, **f) for _ in range(5))
        self.tol = None  # the tolerance tol2 holds the square of
        pdt = _PRECOND_DTYPE.get(precond, torch.float64)
        self.P = torch.eye(n, dtype=pdt, device=device)  # the preconditioner (inverse or Cholesky factor)
        self.owner = None
        rec = graphs and precond != "chol"  # cholesky_solve stays eager (cuSOLVER potrs is not recorded)
        self.graphs = rec
        self.setup = Graphed(self._setup, record=rec, compile=compile)
        self.run_block = Graphed(self._block, record=rec, compile=compile)

    def load(self, owner, F):
        """Make factor number ``owner`` (F) the preconditioner: copied into the recorded buffer when graphs
        read it by address."""
        if self.owner == owner:
            return
        if self.graphs:
            self.P.copy_(F)
        else:
            self.P = F
        self.owner = owner

    def spmv(self, v):
        return (self.vals * v[self.col]).sum(1)

    def apply_precond(self, r):
        if self.precond == "chol":
            return torch.cholesky_solve(r[:, None], self.P)[:, 0]
        if self.P.dtype != torch.float64:
            return torch.mv(self.P, r.to(self.P.dtype)).to(torch.float64)
        return torch.mv(self.P, r)

    def _setup(self):
        """From (data, b, x): the ELL values, r = b - A x, p = P r and the state (x = 0 when b = 0)."""
        self.vals.copy_(self.data[self.src])
        bb = torch.dot(self.b, self.b)
        self.atol2.copy_(self.tol2 * bb)
        self.x.mul_(bb > 0)
        self.r.copy_(self.b - self.spmv(self.x))
        z = self.apply_precond(self.r)
        self.p.copy_(z)
        self.rz.copy_(torch.dot(self.r, z))
        self.rr.copy_(torch.dot(self.r, self.r))
        self.its.zero_()

    def _block(self):
        rz, rr = self.rz, self.rr
        for _ in range(self.block):  # the scalars go back to their buffers once per block
            rz, rr = self._iteration(rz, rr)
        self.rz.copy_(rz)
        self.rr.copy_(rr)

    def _iteration(self, rz, rr):
        """One CG iteration, no host synchronisation: (r.z, r.r) -> their new values."""
        p, r = self.p, self.r
        above = rr > self.atol2  # else alpha = 0: x, r and the rest stay as they are
        self.its.add_(above)
        Ap = self.spmv(p)
        alpha = rz / torch.dot(p, Ap).clamp_min(_TINY) * above
        self.x.addcmul_(alpha, p)
        r.addcmul_(alpha, Ap, value=-1.0)
        z = self.apply_precond(r)
        # flexible (Polak-Ribiere) beta = z.(r - r_old) / rz_old = -alpha z.Ap / rz_old, as the CPU's CG
        # (robust to a slightly nonlinear preconditioner: the float32 inverse rounds r); p = z + beta p
        mbeta = alpha * torch.dot(z, Ap) / rz.clamp_min(_TINY)
        p.copy_(torch.addcmul(z, mbeta, p, value=-1.0))
        return torch.dot(r, z).reshape(1), torch.dot(r, r).reshape(1)

    def state(self):
        """(converged, residual finite, iterations begun above the tolerance): one host synchronisation."""
        rr, atol2, i = torch.cat((self.rr, self.atol2, self.its)).tolist()
        return rr <= atol2, math.isfinite(rr), int(i)


_SERIAL = itertools.count(1)  # names every factor made, process-wide (the workspace's ``owner``)
_WORK: dict = {}  # (device, precond, block, graphs, pattern) -> _Work, one per topology in use


def _work(indptr, indices, device, precond, block, graphs, compile) -> _Work:
    key = (str(device), precond, block, graphs, compile, len(indptr), len(indices), hash(indptr.tobytes()),
           hash(indices.tobytes()))
    w = _WORK.get(key)
    if w is None:
        if len(_WORK) >= 8:  # a few topologies at most; an old one's buffers go
            _WORK.pop(next(iter(_WORK)))
        w = _WORK[key] = _Work(indptr, indices, device, precond, block, graphs, compile)
    return w


class DenseFactorSolver:
    """CG preconditioned by a reused dense factor (Cholesky, or its inverse), refactorised when needed."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, device, tol: float = 1e-6, max_iter: int = 60,
                 refactor_after: int = 20, precond: str = "inv32", refactor_every_solve: bool = False,
                 block: int = 2, graphs: bool | None = None, compile: bool = False,
                 stats: SolveStats | None = None, keep_factors_bytes: int = 1 << 30,
                 refactor_age: int | None = None, cache=None, step_offset: int = 0, factor32: bool = False):
        if precond not in PRECONDS:
            raise ValueError(f"precond must be one of {PRECONDS}, got {precond!r}")
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        indices = np.ascontiguousarray(indices, dtype=np.int64)
        device = torch.device(device)
        g = graphs_wanted(device, graphs)
        self.ws = _work(indptr, indices, device, precond, int(block), g, bool(compile) and precond != "chol")
        self.n = self.ws.n
        self.tol = tol
        self.max_iter = max_iter
        self.refactor_after = refactor_after
        self.refactor_every_solve = refactor_every_solve
        # also refactorise when the current factor was made more than this many substeps away (None: never)
        self.refactor_age = refactor_age
        self._made_at = None  # the substep of the current factor
        self.precond = precond
        self.factor32 = bool(factor32) and precond in _PRECOND_DTYPE
        self.stats = stats if stats is not None else SolveStats()
        self.stats.extra.setdefault("checks", 0)  # host reads of the CG state
        self.F = None  # the current factor (inverse or Cholesky); None: none yet, or A was not SPD
        self._serial = 0  # the current factor's number from _SERIAL
        self._last_its = 0
        # factors made during the forward pass, by substep (as ReusedLUSolver): the adjoint solve of substep i
        # is preconditioned by the one made nearest to i. With a FactorCache (``cache``, factor_cache.py) they
        # live in its ``dense`` table, by absolute substep (this rollout's substep i is step_offset + i), and
        # the forward's solves too start from the kept factor nearest to them, made in an earlier epoch.
        self.step = None
        self.cache = cache
        self.step_offset = int(step_offset)
        self.factors: dict[int, tuple[int, torch.Tensor]] = {} if cache is None else cache.dense
        self.keep_factors_bytes = keep_factors_bytes if cache is None else cache.dense_budget_bytes

    def at_step(self, i: int | None, select: bool = False):
        """Tag the following solves with substep ``i``; with ``select`` switch to the kept factor made nearest
        to it (the backward pass walks the substeps in reverse)."""
        self.step = None if i is None else i + self.step_offset
        if (select or self.cache is not None) and self.factors and i is not None:
            j = min(self.factors, key=lambda k: abs(k - self.step))
            self._serial, self.F = self.factors[j]
            self._made_at = j

    def _keep(self):
        if self.step is None:
            return
        size = self.F.numel() * self.F.element_size()
        used = sum(F.numel() * F.element_size() for _, F in self.factors.values())
        if used + size > self.keep_factors_bytes:
            for k in sorted(self.factors)[1::2]:  # over budget: every other one goes, keeping the spread
                del self.factors[k]
            used = sum(F.numel() * F.element_size() for _, F in self.factors.values())
            if used + size > self.keep_factors_bytes:
                return
        self.factors[self.step] = (self._serial, self.F)

    def _dense(self, data):
        ws = self.ws
        ws.dense.zero_()
        ws.dense.view(-1).index_put_((ws.flat,), data)
        return ws.dense

    def factorize(self, data: torch.Tensor) -> bool:
        """Factorise the current A: True when it is positive definite (the factor becomes the
        preconditioner), False otherwise (no factor)."""
        with record_function("saft.dense.factorize"):
            self.stats.factorizations += 1
            A = self._dense(data)
            L, info = torch.linalg.cholesky_ex(A.float()) if self.factor32 else (None, None)
            if info is None or int(info) != 0:  # float64: asked for, or float32 was not positive definite
                L, info = torch.linalg.cholesky_ex(A)
            if int(info) != 0:
                self.F = None
                return False
            if self.precond == "chol":
                F = L
            else:
                F = torch.cholesky_inverse(L)
                F = 0.5 * (F + F.T)  # exactly symmetric (CG's preconditioner must be)
                F = F.to(_PRECOND_DTYPE.get(self.precond, torch.float64))
            self._serial = next(_SERIAL)
            self.F = F
            self._made_at = self.step
            self._last_its = 0  # a fresh factor converges in a few iterations: read early
            self._keep()
            return True

    def solve(self, data: torch.Tensor, b: torch.Tensor, x0: torch.Tensor | None = None) -> torch.Tensor:
        self.stats.solves += 1
        if self.refactor_every_solve or self._too_old():
            self.F = None
        if self.F is not None:
            x, its = self._pcg(data, b, x0)
            if x is not None:
                if its > self.refactor_after:
                    self.factorize(data)  # also in the adjoint pass: then kept for the earlier substeps
                return x
            self.stats.fallbacks += 1
        if self.factorize(data):
            x, its = self._pcg(data, b, x0)  # with the fresh factor: a few iterations
            if x is not None:
                return x
        return self._direct(data, b)

    def _too_old(self) -> bool:
        return (self.refactor_age is not None and self.step is not None and self._made_at is not None
                and abs(self.step - self._made_at) > self.refactor_age)

    def _pcg(self, data, b, x0):
        """CG from x0 preconditioned by the current factor: (x, iterations), x None on failure."""
        with record_function("saft.dense.pcg"):
            ws = self.ws
            ws.load(self._serial, self.F)
            if ws.tol != self.tol:  # the workspace is shared: solvers of other tolerances may have run
                ws.tol2.fill_(self.tol * self.tol)
                ws.tol = self.tol
            ws.data[: ws.nnz].copy_(data)
            ws.b.copy_(b)
            if x0 is None:
                ws.x.zero_()
            else:
                ws.x.copy_(x0)
            ws.setup()
            k = ws.block
            done = 0
            blocks = max(1, math.ceil(self._last_its / k))  # where the previous solve converged
            while True:
                blocks = max(1, min(blocks, math.ceil((self.max_iter - done) / k)))
                for _ in range(blocks):
                    ws.run_block()
                done += blocks * k
                converged, finite, its = ws.state()
                self.stats.extra["checks"] += 1
                if converged or not finite or done >= self.max_iter:
                    break
                blocks = 1
            self.stats.iterations += its
            if not converged:  # breakdown (A or the factor not SPD), or max_iter (rounded up to a block)
                return None, its
            self._last_its = its
            return ws.x.clone(), its

    def _direct(self, data, b):
        """Dense LU with partial pivoting (exact for any non-singular A), refined to the tolerance."""
        with record_function("saft.dense.direct"):
            A = self._dense(data).clone()
            LU, piv = torch.linalg.lu_factor(A)
            x = torch.linalg.lu_solve(LU, piv, b[:, None])[:, 0]
            atol = self.tol * float(torch.linalg.vector_norm(b))
            for _ in range(4):
                r = b - A @ x
                if float(torch.linalg.vector_norm(r)) <= atol:
                    break
                x = x + torch.linalg.lu_solve(LU, piv, r[:, None])[:, 0]
            return x
