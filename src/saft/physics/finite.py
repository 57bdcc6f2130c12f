"""The rollout's checks for non-finite values (SimulationError names the frame and the substep).

On the CPU each check reads its flag at once. On other devices reading a flag is a host synchronisation that
drains the GPU's queue (one to three per substep, beside the solver's own): there the flags of a frame's
checks are kept on the device and read together by ``flush`` at the end of the frame, and the first failing
check is still the one named. In between, the simulation goes on with the bad values (the solvers' fallbacks
return them without raising), for at most the rest of that frame.
"""

from __future__ import annotations

import torch

from saft.errors import SimulationError


def _error(what, frame, substep):
    return SimulationError(f"non-finite {what} in the cloth simulation at frame {frame}, substep {substep}")


def check_finite(arr, what, frame, substep):
    if not bool(torch.isfinite(arr).all()):
        raise _error(what, frame, substep)


class FiniteChecks:
    """``check(arr, what, frame, substep)``; ``flush()`` after each frame (a no-op on the CPU)."""

    def __init__(self, device: torch.device):
        self.defer = device.type != "cpu"
        self.pending: list = []

    def check(self, arr, what, frame, substep):
        if not self.defer:
            return check_finite(arr, what, frame, substep)
        self.pending.append((torch.isfinite(arr).all(), what, frame, substep))

    def flush(self):
        if not self.pending:
            return
        pending, self.pending = self.pending, []
        ok = torch.stack([p[0] for p in pending]).tolist()
        for good, (_, what, frame, substep) in zip(ok, pending):
            if not good:
                raise _error(what, frame, substep)
