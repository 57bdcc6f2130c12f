"""Preconditioner factors kept from one rollout to the next, by absolute substep (issue 29, item 3).

The shape phase simulates the same frames epoch after epoch with parameters that move a little each time,
so the system matrix A = M + h²K of substep i in this epoch is close to that of substep i in the last one.
Within one rollout it is not close to its neighbours: a cloth hanging in tension changes its transverse
stiffness from substep to substep, and the CPU solver (``solver.ReusedLUSolver``) refactorised every 2-3
substeps (a 32-frame pinned rollout: 45 incomplete LU factorisations for 124 solves, 70 % of the forward
pass). With a ``FactorCache`` the forward pass, like the adjoint pass already did, preconditions substep i
with the kept factor made nearest to it, and refactorises (and keeps) only where CG needs more than the
solver's ``refactor_after`` iterations: in later epochs almost never.

What is kept is only what the numba CG applies (``pcg_numba.factors_from_superlu``: numpy arrays), never
SuperLU's own object, so that the cache is part of the shape phase's checkpoint and a resumed run makes the
same decisions, bit for bit, as an uninterrupted one.

The dense factors of the CUDA solver (``solver_dense.DenseFactorSolver``, R1: a 37.7 MB float32 inverse each)
are kept in ``dense`` the same way, on the device, and are not checkpointed: a resumed run refactorises once
(runs on CUDA are not bit for bit repeatable anyway: nvdiffrast's backward adds with atomics). Without them
every rollout of an epoch began with a fresh factorisation: 178 of them in a 10-frame R1 run of 45 epochs,
1.16 s of its 8.1 s of GPU time (H100, BENCHMARKS.md "GPU").
"""

from __future__ import annotations

import numpy as np


class FactorCache:
    """Factors by absolute substep (frame * substeps + substep): {step: (None, float32?, arrays)}.

    The entries have the layout of ``ReusedLUSolver.factors`` (lu, lu_f32, pre) with lu = None; insertion
    order is kept (it breaks ties between equally near factors) and so is the byte count of the budget."""

    def __init__(self, budget_bytes: int = 128 * 2**20):
        self.entries: dict[int, tuple] = {}
        self.nbytes = 0
        # it is written with every checkpoint (every 20 s by default): over this, every other factor goes
        # (a 25 x 25 cloth's factor is ~0.6 MB: the 32-frame benchmark scenes' checkpoints grew from 5 to
        # 78 MB, under this budget, so the measured runs never thinned)
        self.budget_bytes = budget_bytes
        self.dense: dict[int, tuple] = {}   # {step: (serial, factor tensor)}: solver_dense's, not checkpointed
        self.dense_budget_bytes = 1 << 30

    def __len__(self) -> int:
        return len(self.entries)

    @staticmethod
    def entry_nbytes(pre) -> int:
        return int(sum(a.nbytes for a in pre))

    def state_dict(self) -> dict:
        return {"entries": [(int(k), bool(f32), [np.asarray(a) for a in pre]) for k, (_, f32, pre) in self.entries.items()],
                "nbytes": int(self.nbytes)}

    def load_state_dict(self, saved: dict) -> None:
        self.entries = {int(k): (None, bool(f32), tuple(pre)) for k, f32, pre in saved.get("entries", [])}
        self.nbytes = int(saved.get("nbytes", sum(self.entry_nbytes(e[2]) for e in self.entries.values())))
