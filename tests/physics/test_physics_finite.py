"""The rollout's non-finite checks (saft.physics.finite)."""

import pytest
import torch

from saft.errors import SimulationError
from saft.physics.finite import FiniteChecks


def test_deferred_finite_checks_name_the_first_failing_substep():
    """On a GPU the rollout's finite checks are read once per frame; the error still names the first bad
    (frame, substep). Exercised here with CPU tensors under a CUDA device's rule."""
    c = FiniteChecks(torch.device("cuda"))
    ok, bad = torch.ones(3), torch.tensor([1.0, float("nan")])
    c.check(ok, "velocity", 2, 0)
    c.check(bad, "velocity", 2, 1)
    c.check(bad * float("inf"), "adjoint", 2, 2)
    assert len(c.pending) == 3  # nothing read yet
    with pytest.raises(SimulationError, match=r"non-finite velocity .* frame 2, substep 1"):
        c.flush()
    assert not c.pending
    c.check(ok, "velocity", 3, 0)
    c.flush()
    cpu = FiniteChecks(torch.device("cpu"))
    with pytest.raises(SimulationError, match=r"frame 4, substep 3"):
        cpu.check(bad, "adjoint", 4, 3)  # at once
