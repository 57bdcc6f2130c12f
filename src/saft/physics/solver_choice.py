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
    # the explicit inverse in float32 (one GEMV per application), made from a float32 factorisation
    "dense": dict(precond="inv32", factor32=True),
    "dense64": dict(precond="inv64"),
    # the inverse in bfloat16, half the GEMV's traffic: auto's choice off the CPU
    "densebf16": dict(precond="invbf16", factor32=True),
    "densechol": dict(precond="chol"),  # the Cholesky factor, two triangular solves per application
    "direct": dict(precond="chol", refactor_every_solve=True),  # a fresh factor every solve
}
CUDA_DEFAULT = "densebf16"  # R1 on one H100: 93-119 s, CD2 median 0.445 of 3 (BENCHMARKS.md, GPU, third session)
SOLVERS = ("auto", "lu", "cholmod", "cg", *DENSE_SOLVERS)
# For A/B runs of whole reconstructions on a GPU (benchmarks/gpu_check.sh): the dense variant "auto" takes off
# the CPU instead of CUDA_DEFAULT, a name or a spec of dense_variant, e.g. dense or densebf16:f32=0:age=12
ENV_DENSE_SOLVER = "SAFT_DENSE_SOLVER"
_SPEC_KEYS = {"after": ("refactor_after", int), "age": ("refactor_age", int), "block": ("block", int),
              "f32": ("factor32", lambda v: bool(int(v)))}


def dense_variant(spec: str) -> str:
    """A dense solver name, registered in DENSE_SOLVERS (this process) when it is a spec
    "<dense solver>[:N[:M]][:key=value...]": N refactor_after, M refactor_age, or named: after=N, age=M,
    block=B (CG iterations between host reads), f32=1 (float32 factorisations). ValueError when malformed."""
    base, *opts = spec.split(":")
    if base not in DENSE_SOLVERS or len(opts) > 4:
        raise ValueError(f"{spec!r} is not <dense solver>[:N[:M]][:key=value] ({', '.join(DENSE_SOLVERS)}; keys "
                         f"{', '.join(_SPEC_KEYS)})")
    kw = {}
    for pos, opt in enumerate(opts):
        key, _, val = opt.rpartition("=")
        key = key or ("after", "age")[min(pos, 1)]
        if key not in _SPEC_KEYS:
            raise ValueError(f"{spec!r}: unknown option {key!r} (keys {', '.join(_SPEC_KEYS)})")
        field, conv = _SPEC_KEYS[key]
        try:
            kw[field] = conv(val)
        except ValueError:
            raise ValueError(f"{spec!r}: {key}={val!r} is not an integer") from None
    if kw:
        DENSE_SOLVERS[spec] = {**DENSE_SOLVERS[base], **kw}
    return spec


def solver_for(topology: ClothTopology, solver: str, tol: float, stats: SolveStats, compile: bool = False,
                cache=None, first_step: int = 0):
    if solver == "auto":
        # never depends on what is importable: CHOLMOD (opt-in) gives different numbers within the tolerance,
        # and reconstructions are sensitive to that noise. Other devices: the reused dense factor (solver_dense)
        if topology.device.type == "cpu":
            solver = "lu"
        else:
            try:
                solver = dense_variant(os.environ.get(ENV_DENSE_SOLVER, CUDA_DEFAULT))
            except ValueError as exc:
                raise ValueError(f"{ENV_DENSE_SOLVER}: {exc}") from None
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


__all__ = ["CUDA_DEFAULT", "DENSE_SOLVERS", "ENV_DENSE_SOLVER", "SOLVERS", "dense_variant", "solver_for"]
