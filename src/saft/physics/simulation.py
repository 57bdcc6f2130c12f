"""Linearised backward Euler (Baraff-Witkin, one Newton step) and the differentiable rollout.

One substep (h = frame_dt / substeps), with v <- d * v first (velocity damping):
    (M + h^2 K(x)) v1 = M (d v) + h (f(x) + M a_ext),   f = -dE/dx,   x1 = x + h v1
a_ext = a_const + a_vert[k] during the substeps from frame k to frame k + 1.

Soft anchors (params.anchor = w, per unit mass): f += -m w (x - p), with h^2 m w on A's diagonal.

Air drag (params.log10_drag = log10 c, optional; saft.physics.drag): f += F_drag(x, v), the pressure of still
air along each triangle's normal at the substep's start, explicit (the system matrix is unchanged).

Pinned vertices: their velocity is prescribed, v1_P = (target - x_P) / h, and the system is solved for the
free DOFs only (rows/columns of P replaced by the identity); x1_P is set to the target exactly.

``rollout`` is one ``torch.autograd.Function``: the forward pass runs the whole simulation without autograd
and keeps only (x, v, v1) per substep; the backward pass runs the discrete adjoint in reverse, with one
adjoint linear solve per substep (the same reused-factorisation solver), closed-form element derivatives
and the third-derivative contraction d/dx (lam^T K(x) v1). Autograd never sees a solver iteration.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from saft.physics.drag import drag_force, drag_vjp
from saft.physics.energy import LN10, ElementEval  # noqa: F401 (ElementEval: tests patch it here)
from saft.physics.finite import FiniteChecks, check_finite
from saft.physics.kernels import StepKernels
from saft.physics.rollout_inputs import anchor_inputs, drag_input, frame_rows
from saft.physics.factor_cache import FactorCache
from saft.physics.solver import SolveStats, sparse_csr
from saft.physics.solver_choice import DENSE_SOLVERS, SOLVERS, solver_for  # noqa: F401 (DENSE_SOLVERS, SOLVERS: API)
from saft.physics.topology import ClothTopology

GRAVITY = (0.0, -9.81, 0.0)
DEFAULT_LOG10_Y = math.log10(200.0)  # paper, supplementary table: Y = 200, B = 1e-3, S = 1e-4
DEFAULT_LOG10_B = -3.0
DEFAULT_LOG10_S = -4.0
DEFAULT_DAMPING = 0.9  # v <- 0.9 v per substep (paper, supplementary "Damping")
DEFAULT_SUBSTEPS = 4  # simulation steps per video frame
LOG10_LIMITS = {"log10_Y": (1.0, 3.0), "log10_B": (-5.0, -2.0), "log10_S": (-4.0, -2.0)}  # REFERENCE.md


@dataclass
class PhysicsParams:
    """The optimizable simulation parameters (all tensors; any of them may require grad).

    log10_Y, log10_B, log10_S: 0-dim, log10 of the stretch / bend / shear stiffness (SI units).
    damping: 0-dim velocity scale d applied before every substep.
    a_const: (3,) constant acceleration (gravity + mean wind), m/s^2.
    a_vert: (N - 1, V, 3) per-vertex per-frame accelerations, or None (zero); a rollout of fewer frames
            uses the first ones.
    anchor: (V,) anchor stiffness per unit mass w (s^-2, >= 0), or None (no anchors): vertex i is pulled
            towards its anchor position p_i by the force -m_i w_i (x_i - p_i), a zero-length spring treated
            implicitly like the cloth's own forces (a soft pin; w h^2 >> 1 holds the vertex in place).
    log10_drag: 0-dim log10 of the air drag coefficient c (kg/m^3, saft.physics.drag), or None (no drag).
    """

    log10_Y: torch.Tensor
    log10_B: torch.Tensor
    log10_S: torch.Tensor
    damping: torch.Tensor
    a_const: torch.Tensor
    a_vert: torch.Tensor | None = None
    anchor: torch.Tensor | None = None
    log10_drag: torch.Tensor | None = None

    @classmethod
    def default(cls, num_frames: int | None = None, num_vertices: int | None = None, *, device=None,
                dtype=torch.float64, requires_grad: bool = False) -> "PhysicsParams":
        """Paper defaults: Y = 200, B = 1e-3, S = 1e-4, d = 0.9, a_const = gravity, a_vert = 0."""
        f = dict(device=device, dtype=dtype)
        p = cls(
            log10_Y=torch.tensor(DEFAULT_LOG10_Y, **f),
            log10_B=torch.tensor(DEFAULT_LOG10_B, **f),
            log10_S=torch.tensor(DEFAULT_LOG10_S, **f),
            damping=torch.tensor(DEFAULT_DAMPING, **f),
            a_const=torch.tensor(GRAVITY, **f),
            a_vert=None if num_frames is None else torch.zeros(num_frames - 1, num_vertices, 3, **f),
        )
        if requires_grad:
            for t in p.tensors():
                if t is not None:
                    t.requires_grad_(True)
        return p

    def tensors(self):
        """The parameters in constructor order; the anchors and the drag only when there are any."""
        base = (self.log10_Y, self.log10_B, self.log10_S, self.damping, self.a_const, self.a_vert)
        return base + tuple(t for t in (self.anchor, self.log10_drag) if t is not None)


class _Sim:
    """Everything a rollout needs besides the differentiable inputs."""

    def __init__(self, topology, num_frames, substeps, frame_dt, pinned, pinned_positions, hessian, solver, tol,
                 compile=None, kernels=None, anchor_positions=None):
        t = topology
        self.anchor_positions = anchor_positions
        self.t = t
        self.V = t.num_vertices
        self.N = int(num_frames)
        self.substeps = int(substeps)
        self.h = float(frame_dt) / self.substeps
        self.mode = hessian
        self.solver_kind = solver
        self.tol = tol
        self.keep_matrices_bytes = 512 * 2**20
        self.kernels = StepKernels(t, hessian, compile=compile, backend=kernels)
        self.stats = SolveStats()
        self.stats_out = None  # the caller's stats dict (backward counters are added as bwd_*)
        self.factor_cache = None  # a FactorCache shared with other rollouts ("lu" and the dense solvers)
        self.first_step = 0       # the absolute substep of this rollout's first one, the cache's key
        self.on_frame = None      # called with (frame, its positions) as each frame is done (forward pass)
        self.use_numpy = (solver in ("lu", "cholmod")) or (solver == "auto" and t.device.type == "cpu")
        self.m3 = t.mass[:, None].expand(-1, 3)  # (V, 3)
        self.mass_diag = t.mass.repeat_interleave(3)  # (3V,)
        self.pinned = None
        if pinned is not None:
            p = torch.as_tensor(pinned, device=t.device, dtype=torch.long).reshape(-1)
            if p.numel() == 0:
                p = None
            self.pinned = p
        if self.pinned is not None:
            P = self.pinned
            pdof = torch.zeros(3 * self.V, dtype=torch.bool, device=t.device)
            pdof.view(self.V, 3)[P] = True
            self.pdof = pdof
            indptr = t.csr_indptr
            rows = np.repeat(np.arange(3 * self.V), np.diff(indptr))
            pd = pdof.cpu().numpy()
            keep = ~(pd[rows] | pd[t.csr_indices])
            self.keep = torch.as_tensor(keep, device=t.device, dtype=t.dtype)
            self.pin_diag = t.diag_idx[pdof]
            if pinned_positions is not None:
                pp = torch.as_tensor(pinned_positions, device=t.device, dtype=t.dtype)
                if pp.shape != (self.N, P.numel(), 3):
                    raise ValueError(
                        f"pinned_positions must have shape ({self.N}, {P.numel()}, 3), got {tuple(pp.shape)}"
                    )
                self.pin_targets = pp.detach()
            else:
                self.pin_targets = None

    # ------------------------------------------------------------------ helpers
    def target(self, x0, k, s):
        """Prescribed pinned positions at the end of substep s of frame k (linear within the frame)."""
        if self.pin_targets is None:
            return x0[self.pinned]
        w = (s + 1) / self.substeps
        return (1.0 - w) * self.pin_targets[k] + w * self.pin_targets[k + 1]

    def anchor_system(self, A, anchor_mass):
        """A + h^2 diag(m w): the anchors' springs in the system matrix (anchor_mass = m w, (V, 3))."""
        if anchor_mass is None:
            return A
        return A.index_add(0, self.t.diag_idx, (self.h * self.h) * anchor_mass.reshape(-1))

    def system(self, ev: ElementEval):
        """(K data, A data) with A = M + h^2 K, before pinning."""
        K = ev.hessian_values()
        A = (self.h * self.h) * K
        A.index_add_(0, self.t.diag_idx, self.mass_diag)
        return K, A

    def new_solver(self):
        return solver_for(self.t, self.solver_kind, self.tol, self.stats, self.kernels.use_compile, self.factor_cache,
                           self.first_step)

    def spmv(self, data, vec):
        t = self.t
        if self.use_numpy:
            import scipy.sparse as sp

            n = 3 * self.V
            M = sp.csr_matrix((data.numpy(), t.csr_indices, t.csr_indptr), shape=(n, n), copy=False)
            return torch.from_numpy(M @ vec.numpy())
        crow = torch.as_tensor(t.csr_indptr, device=t.device)
        col = torch.as_tensor(t.csr_indices, device=t.device)
        return sparse_csr(crow, col, data, 3 * self.V) @ vec

    def lin_solve(self, solver, data, b, guess):
        if self.use_numpy:
            return torch.from_numpy(solver.solve(data.numpy(), b.numpy(), guess.numpy()))
        return solver.solve(data, b, guess)


def _one_cpu_thread(fn):
    """Run ``fn`` with one torch intra-op thread (the caller's count is restored afterwards).

    Every array of a substep is small (3 x 6k hinges on R1), so a second thread gains nothing, while on a
    shared machine OpenMP's waiting threads cost several times the CPU time: the 32x32 benchmark measured
    25 s CPU / 52 s wall with 2 threads against 3.5 s / 5.7 s with 1. The results do not depend on it
    (bitwise the same with any thread count)."""

    @functools.wraps(fn)
    def wrapper(*args):
        threads = torch.get_num_threads()
        if threads == 1:
            return fn(*args)
        torch.set_num_threads(1)
        try:
            return fn(*args)
        finally:
            torch.set_num_threads(threads)

    return wrapper


class _RolloutFn(torch.autograd.Function):
    @staticmethod
    @_one_cpu_thread
    def forward(ctx, sim: _Sim, x0, v0, lY, lB, lS, damping, a_const, a_vert, anchor, l_drag):
        t = sim.t
        Y, B, S = (10.0 ** float(lY)), (10.0 ** float(lB)), (10.0 ** float(lS))
        d = float(damping)
        h = sim.h
        N, ns, V = sim.N, sim.substeps, sim.V
        for name, val in (("log10_Y", lY), ("log10_B", lB), ("log10_S", lS), ("damping", damping),
                          ("a_const", a_const), ("x0", x0), ("v0", v0)):
            check_finite(val, f"input {name}", 0, 0)
        positions = torch.empty(N, V, 3, dtype=x0.dtype, device=x0.device)
        positions[0] = x0
        if sim.on_frame is not None:
            sim.on_frame(0, positions[0])
        saved = torch.empty(max(N - 1, 0) * ns, 3, V, 3, dtype=x0.dtype, device=x0.device)
        x = x0.clone()
        v = v0.clone()
        solver = sim.new_solver()
        m3 = sim.m3
        pinned = sim.pinned
        kern = sim.kernels
        Yt, Bt, St, hh = (x0.new_tensor(c) for c in (Y, B, S, h * h))
        # keep the system matrices for the adjoint pass when they fit the memory budget
        keep_A = (N - 1) * ns * t.nnz * x0.element_size() <= sim.keep_matrices_bytes
        A_saved = []
        anchor_mass = None if anchor is None else m3 * anchor.detach()[:, None]  # m w, (V, 3)
        if anchor is not None:
            check_finite(anchor, "input anchor", 0, 0)
            anchor_at = sim.anchor_positions
        drag_c = None if l_drag is None else 10.0 ** l_drag.detach()
        if drag_c is not None:
            check_finite(l_drag, "input log10_drag", 0, 0)
        checks = FiniteChecks(x0.device)  # on a GPU read once per frame
        for k in range(N - 1):
            a = a_const if a_vert is None else a_const + a_vert[k]
            checks.check(a, "external acceleration", k, 0)
            for s in range(ns):
                i = k * ns + s
                saved[i, 0] = x
                saved[i, 1] = v
                vd = d * v
                gradE, A = kern.forward(x, Yt, Bt, St, hh, sim.mass_diag, t.diag_idx)  # (V, 3), (nnz,)
                if anchor_mass is not None:
                    gradE = gradE + anchor_mass * (x - anchor_at)
                    A = sim.anchor_system(A, anchor_mass)
                if drag_c is not None:  # explicit: at the substep's start (x, v)
                    gradE = gradE - drag_force(x, v, t.triangles, drag_c)
                b = (m3 * vd + h * (m3 * a - gradE)).reshape(-1)
                if pinned is not None:
                    tgt = sim.target(x0, k, s)
                    vP = (tgt - x[pinned]) / h
                    wfull = torch.zeros_like(x)
                    wfull[pinned] = vP
                    b = b - sim.spmv(A, wfull.reshape(-1))
                    b.view(V, 3)[pinned] = vP
                    A = A * sim.keep
                    A[sim.pin_diag] = 1.0
                if keep_A:
                    A_saved.append(A)
                if hasattr(solver, "at_step"):
                    solver.at_step(i)
                v1 = sim.lin_solve(solver, A, b, vd.reshape(-1)).reshape(V, 3)
                if pinned is not None:
                    v1[pinned] = vP
                checks.check(v1, "velocity", k, s)
                x = x + h * v1
                if pinned is not None:
                    x[pinned] = tgt
                v = v1
                saved[i, 2] = v1
            checks.flush()
            positions[k + 1] = x
            if sim.on_frame is not None:   # the caller's work on a finished frame, while the next is simulated
                sim.on_frame(k + 1, positions[k + 1])
        ctx.sim = sim
        ctx.solver = solver
        ctx.A_saved = A_saved if keep_A else None
        empty = x0.new_empty(0)
        ctx.save_for_backward(x0, saved, lY, lB, lS, damping, a_const, a_vert if a_vert is not None else empty,
                              anchor if anchor is not None else empty, l_drag if l_drag is not None else empty)
        ctx.has_avert = a_vert is not None
        ctx.has_anchor = anchor is not None
        ctx.has_drag = l_drag is not None
        return positions

    @staticmethod
    @_one_cpu_thread
    def backward(ctx, grad_pos):
        sim: _Sim = ctx.sim
        x0, saved, lY, lB, lS, damping, a_const, a_vert, anchor, l_drag = ctx.saved_tensors
        t = sim.t
        Y, B, S = (10.0 ** float(lY)), (10.0 ** float(lB)), (10.0 ** float(lS))
        d = float(damping)
        h = sim.h
        N, ns, V = sim.N, sim.substeps, sim.V
        m3 = sim.m3
        pinned = sim.pinned
        solver = ctx.solver  # starts from the forward pass's last factorisation
        kern = sim.kernels
        Yt, Bt, St, hh, ht = (x0.new_tensor(c) for c in (Y, B, S, h * h, h))
        grad_pos = grad_pos.to(x0.dtype)
        gx = grad_pos[N - 1].clone()
        gv = torch.zeros_like(x0)
        g_a = torch.zeros(max(N - 1, 0), V, 3, dtype=x0.dtype, device=x0.device)
        gY = torch.zeros((), dtype=x0.dtype, device=x0.device)
        gB = torch.zeros_like(gY)
        gS = torch.zeros_like(gY)
        gd = torch.zeros_like(gY)
        lam_guess = torch.zeros(3 * V, dtype=x0.dtype, device=x0.device)
        anchor_mass = m3 * anchor[:, None] if ctx.has_anchor else None
        g_anchor = torch.zeros(V, 3, dtype=x0.dtype, device=x0.device) if ctx.has_anchor else None
        drag_c = 10.0 ** l_drag if ctx.has_drag else None
        g_drag = torch.zeros_like(gY)
        checks = FiniteChecks(x0.device)
        for k in range(N - 2, -1, -1):
            for s in range(ns - 1, -1, -1):
                i = k * ns + s
                x, v, v1 = saved[i, 0], saved[i, 1], saved[i, 2]
                if pinned is not None:
                    gx[pinned] = 0.0
                    gv[pinned] = 0.0
                if ctx.A_saved is not None:
                    A = ctx.A_saved[i]
                else:
                    A = sim.anchor_system(kern.forward(x, Yt, Bt, St, hh, sim.mass_diag, t.diag_idx)[1], anchor_mass)
                    if pinned is not None:
                        A = A * sim.keep
                        A[sim.pin_diag] = 1.0
                rhs = (gv + h * gx).reshape(-1)
                if hasattr(solver, "at_step"):
                    solver.at_step(i, select=True)
                lam = sim.lin_solve(solver, A, rhs, lam_guess)
                checks.check(lam, "adjoint", k, s)
                lam_guess = lam
                lamV = lam.view(V, 3)
                # d/dx of lam.(b - A v1): -h (true Hessian) lam - h^2 d/dx(lam^T K(x) v1), and the
                # stiffness terms -h lam.dE_k/dx - h^2 lam^T K_k v1 (each linear in its stiffness)
                dgx, dY, dB, dS = kern.adjoint(x, lamV, v1, Yt, Bt, St, ht)
                gx = gx + dgx
                if anchor_mass is not None:
                    # lam.(b - A v1) holds -h m w lam.(x + h v1 - p): d/dx = -h m w lam, d/dw = -h m lam.(x1 - p)
                    gx = gx - h * anchor_mass * lamV
                    g_anchor -= h * (m3 * lamV) * (x + h * v1 - sim.anchor_positions)
                mlam = m3 * lamV
                gd += (mlam * v).sum()
                g_a[k] += h * mlam
                gY += dY
                gB += dB
                gS += dS
                gv = d * mlam
                if drag_c is not None:
                    # lam.(b - A v1) holds h lam.F_drag(x, v): its x, v and c derivatives
                    dx, dv, dc = drag_vjp(x, v, t.triangles, drag_c, lamV)
                    gx = gx + h * dx
                    gv = gv + h * dv
                    g_drag += h * dc
                checks.check(gx, "position adjoint", k, s)
            checks.flush()
            gx = gx + grad_pos[k]
        ctx.A_saved = None
        ctx.solver = None  # frees the kept factors
        if sim.stats_out is not None:
            tot = sim.stats.as_dict()
            sim.stats_out.update({f"bwd_{k}": tot[k] - sim.stats_out.get(k, 0) for k in tot})
        if pinned is not None:
            # pinned targets are constants; x0 at pinned vertices only reaches positions[0]
            gx[pinned] = grad_pos[0][pinned]
            gv[pinned] = 0.0
        g_const = g_a.sum(dim=(0, 1))
        return (
            None,
            gx,
            gv,
            gY * LN10,  # each term is linear in its stiffness k, so d/dlog10 k = ln10 * (term)
            gB * LN10,
            gS * LN10,
            gd,
            g_const,
            g_a if ctx.has_avert else None,
            g_anchor.sum(dim=1) if ctx.has_anchor else None,
            g_drag * drag_c * LN10 if ctx.has_drag else None,  # dc/dlog10 c = c ln10
        )


def rollout(
    topology: ClothTopology,
    x0: torch.Tensor,
    v0: torch.Tensor | None = None,
    params: PhysicsParams | None = None,
    *,
    num_frames: int,
    substeps: int = DEFAULT_SUBSTEPS,
    frame_dt: float = 0.02,
    pinned=None,
    pinned_positions=None,
    hessian: str = "projected",
    solver: str = "auto",
    tol: float = 1e-6,
    stats: dict | None = None,
    compile: bool | None = None,
    kernels: str | None = None,
    anchor_positions: torch.Tensor | None = None,
    factor_cache: FactorCache | None = None,
    first_step: int = 0,
    on_frame: Callable[[int, torch.Tensor], None] | None = None,
) -> torch.Tensor:
    """Simulate ``num_frames`` video frames from (x0, v0); returns positions (num_frames, V, 3) with
    positions[0] = x0. Differentiable w.r.t. x0, v0 and every tensor in ``params``.

    pinned: vertex indices held exactly; at x0 (pinned_positions None) or at ``pinned_positions``
    (num_frames, P, 3), linearly interpolated within a frame's substeps (targets get no gradient).
    hessian: "projected" (PSD element Hessians, default) or "exact" (true Hessian, may be indefinite).
    solver: "auto" ("lu" on CPU, whatever is installed; "densebf16" on other devices), "lu" (CG preconditioned
    by a reused incomplete LU, SuperLU), "cholmod" (opt-in: CG preconditioned by a CHOLMOD Cholesky factor,
    needs scikit-sparse; non-SPD falls back to LU), "cg" (Jacobi-preconditioned CG in torch), or, in torch on
    any device, CG preconditioned by a reused dense Cholesky factor (solver_dense): "densebf16" (its inverse
    in bfloat16), "dense" (in float32; both from float32 factorisations), "dense64" (the inverse in float64),
    "densechol" (the factor's triangular solves) or "direct" (a fresh factor every solve).
    tol: relative residual of every linear solve. stats: if a dict, receives solver counters (forward;
    the backward's are added as bwd_* when it runs).
    compile: torch.compile the per-substep element kernels (None: the SAFT_PHYSICS_COMPILE environment
    variable, off by default; falls back to eager with a warning if compilation fails).
    kernels: element kernel backend, "auto" (numba on CPU float64 with the projected Hessian unless compile
    is on, else torch), "numba" or "torch" (None: the SAFT_PHYSICS_KERNELS environment variable, "auto").
    anchor_positions: (V, 3) where params.anchor's springs pull (None: x0); constants, no gradient.
    factor_cache: a ``FactorCache`` kept across rollouts of the same frames ("lu" and the dense solvers): the
    forward pass preconditions each substep with the kept factor nearest to it, as the adjoint does, and
    keeps the factors it makes; ``first_step`` is the absolute substep of this rollout's first substep
    (frame * substeps for a rollout that starts at that frame). Results agree with a rollout without it to
    the solver tolerance.
    on_frame: called in the forward pass with (frame, its positions (V, 3)) as each frame is done, frame 0
    included: the caller can start work on it while the next frame is simulated (the positions are the
    returned tensor's row: read them, do not write).
    Raises SimulationError (naming frame and substep) on NaN/inf.
    """
    t = topology
    dev, dt = t.device, t.dtype
    x0 = torch.as_tensor(x0).to(device=dev, dtype=dt)
    if x0.shape != (t.num_vertices, 3):
        raise ValueError(f"x0 must have shape ({t.num_vertices}, 3), got {tuple(x0.shape)}")
    v0 = torch.zeros_like(x0) if v0 is None else torch.as_tensor(v0).to(device=dev, dtype=dt)
    if params is None:
        params = PhysicsParams.default(device=dev, dtype=dt)
    if num_frames < 1:
        raise ValueError("num_frames must be >= 1")
    a_vert = frame_rows(params.a_vert, "a_vert", num_frames, (t.num_vertices, 3), dev, dt)
    anchor, anchor_positions = anchor_inputs(params.anchor, anchor_positions, x0, t.num_vertices, dev, dt)
    l_drag = drag_input(params.log10_drag, t.triangles, dev, dt)
    sim = _Sim(t, num_frames, substeps, frame_dt, pinned, pinned_positions, hessian, solver, tol, compile,
               kernels, anchor_positions if anchor is not None else None)
    sim.stats_out = stats
    sim.factor_cache, sim.first_step = factor_cache, int(first_step)
    sim.on_frame = on_frame
    f = dict(device=dev, dtype=dt)

    def sc(v):
        return torch.as_tensor(v).to(**f).reshape(())

    out = _RolloutFn.apply(
        sim, x0, v0, sc(params.log10_Y), sc(params.log10_B), sc(params.log10_S), sc(params.damping),
        torch.as_tensor(params.a_const).to(**f).reshape(3), a_vert, anchor, l_drag,
    )
    if stats is not None:
        stats.update(sim.stats.as_dict())
    return out
