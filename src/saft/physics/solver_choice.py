"""Which linear solver a rollout uses: the solver names of ``saft.physics.rollout(..., solver=)`` and their
classes (solver: the CPU's reused incomplete LU, CHOLMOD, Jacobi CG; solver_dense: the reused dense factor)."""

from __future__ import annotations

import os

import torch

from saft.physics import solver as _solver
from saft.physics.solver import CholmodPCGSolver, JacobiCGSolver, ReusedLUSolver, SolveStats
from saft.physics.solver_dense import DenseFactorSolver
from saft.physics.topology import ClothTopology

# solver name -> DenseFactorSolver options (solver_dense): the reused dense factor's variants
DENSE_SOLVERS = {
    "dense": dict(precond="inv32"),  # explicit inverse in float32, one GEMV per application
    "dense64": dict(precond="inv64"),
    "densebf16": dict(precond="invbf16"),  # the inverse in bfloat16: half the GEMV's traffic
    "densechol": dict(precond="chol"),  # the Cholesky factor, two triangular solves per application
    "direct": dict(precond="chol", refactor_every_solve=True),  # a fresh factor every solve
}
SOLVERS = ("auto", "lu", "cholmod", "cg", *DENSE_SOLVERS)
# For A/B runs of whole reconstructions on a GPU (benchmarks/gpu_check.sh): the dense variant "auto" takes off
# the CPU, e.g. densebf16 (0.350 s against dense's 0.408 s for R1's template on an H100, not yet run on R1)
ENV_DENSE_SOLVER = "SAFT_DENSE_SOLVER"


def solver_for(topology: ClothTopology, solver: str, tol: float, stats: SolveStats, compile: bool = False,
                cache=None, first_step: int = 0):
    if solver == "auto":
        # never depends on what is importable: CHOLMOD (opt-in) gives different numbers within the tolerance,
        # and reconstructions are sensitive to that noise. Other devices: the reused dense factor (solver_dense)
        if topology.device.type == "cpu":
            solver = "lu"
        else:
            solver = os.environ.get(ENV_DENSE_SOLVER, "dense")
            if solver not in DENSE_SOLVERS:
                raise ValueError(f"{ENV_DENSE_SOLVER}={solver!r} is not one of {', '.join(DENSE_SOLVERS)}")
    if solver in DENSE_SOLVERS:
        return DenseFactorSolver(topology.csr_indptr, topology.csr_indices, topology.device, tol=tol, stats=stats,
                                 compile=compile, cache=cache, step_offset=first_step, **DENSE_SOLVERS[solver])
    if solver == "cholmod":
        if not _solver.HAVE_CHOLMOD:   # read at call time: tests set it
            raise ValueError("solver='cholmod' needs scikit-sparse (sksparse.cholmod), which is not importable")
        return CholmodPCGSolver(topology.csr_indptr, topology.csr_indices, tol=tol, stats=stats)
    if solver == "lu":
        return ReusedLUSolver(topology.csr_indptr, topology.csr_indices, tol=tol, stats=stats, cache=cache,
                              step_offset=first_step)
    if solver == "cg":
        dev = topology.device
        crow = torch.as_tensor(topology.csr_indptr, device=dev, dtype=torch.int64)
        col = torch.as_tensor(topology.csr_indices, device=dev, dtype=torch.int64)
        return JacobiCGSolver(crow, col, topology.diag_idx, tol=tol, stats=stats)
    raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")


__all__ = ["DENSE_SOLVERS", "ENV_DENSE_SOLVER", "SOLVERS", "solver_for"]
