"""The shape phase's backtracking (saft.reconstruct.step_guard)."""

import math

import pytest
import torch

from saft.reconstruct.optim import ClippedAdam, ParamSpec
from saft.reconstruct.step_guard import StepGuard


def _run(guard: StepGuard, epochs: int = 60, lr: float = 2.0) -> tuple[list[float], StepGuard]:
    """Adam with a learning rate far too large for f(x) = Σ |x|: without a guard it keeps overshooting."""
    x = torch.tensor([3.0, -2.0], dtype=torch.float64, requires_grad=True)
    opt = ClippedAdam([ParamSpec("x", x, lr)], clip=1e9, quantile=1.0)
    losses = []
    for _ in range(epochs):
        x.grad = None
        loss = x.abs().sum()
        loss.backward()
        losses.append(float(loss.detach()))
        guard.check(frames=1, loss=float(loss.detach()), tensors={"x": x}, optimizer=opt)
        opt.set_lr_factor(guard.lr_scale)
        opt.step()
    return losses, guard


def test_guard_off_changes_nothing():
    losses, guard = _run(StepGuard(ratio=0.0, decay=0.5))
    assert guard.backtracks == 0 and guard.lr_scale == 1.0
    assert min(losses[30:]) > 0.1         # the oversized steps never settle


def test_guard_backtracks_and_converges():
    unguarded, _ = _run(StepGuard(ratio=0.0, decay=0.5))
    losses, guard = _run(StepGuard(ratio=1.3, decay=0.5))
    assert guard.backtracks >= 2 and guard.lr_scale == pytest.approx(0.5 ** guard.backtracks)
    assert max(losses[40:]) < 0.05 and max(unguarded[40:]) > 0.3


def test_rollback_restores_parameters_gradients_and_optimizer_state():
    x = torch.tensor([1.0, 2.0], dtype=torch.float64, requires_grad=True)
    opt = ClippedAdam([ParamSpec("x", x, 0.1)])
    guard = StepGuard(ratio=1.5, decay=0.25)
    x.grad = torch.tensor([0.5, -0.5], dtype=torch.float64)
    assert not guard.check(frames=4, loss=1.0, tensors={"x": x}, optimizer=opt)   # first loss: the snapshot
    opt.step()
    moved = x.detach().clone()
    x.grad = torch.tensor([9.0, 9.0], dtype=torch.float64)
    assert not guard.check(frames=4, loss=1.4, tensors={"x": x}, optimizer=opt)   # within the ratio
    opt.step()
    x.grad = torch.tensor([7.0, 7.0], dtype=torch.float64)
    assert guard.check(frames=4, loss=1.6, tensors={"x": x}, optimizer=opt)       # a jump: roll back
    assert torch.equal(x.detach(), torch.tensor([1.0, 2.0], dtype=torch.float64))
    assert torch.equal(x.grad, torch.tensor([0.5, -0.5], dtype=torch.float64))
    assert guard.lr_scale == 0.25 and guard.backtracks == 1
    opt.set_lr_factor(guard.lr_scale)
    opt.step()   # the restored Adam state is the one before its first step: the same direction, a quarter of it
    assert torch.allclose(x.detach() - torch.tensor([1.0, 2.0], dtype=torch.float64),
                          (moved - torch.tensor([1.0, 2.0], dtype=torch.float64)) * 0.25)


def test_new_frame_count_starts_a_new_reference_and_state_round_trips():
    x = torch.zeros(1, requires_grad=True)
    opt = ClippedAdam([ParamSpec("x", x, 0.1)])
    guard = StepGuard(ratio=1.2, decay=0.5)
    x.grad = torch.ones(1)
    guard.check(frames=3, loss=1.0, tensors={"x": x}, optimizer=opt)
    assert not guard.check(frames=4, loss=5.0, tensors={"x": x}, optimizer=opt)   # more frames: higher is fine
    assert guard.lowest == 5.0
    assert not guard.check(frames=4, loss=math.nan, tensors={"x": x}, optimizer=opt)
    guard.lr_scale, guard.backtracks = 0.125, 3
    other = StepGuard(ratio=1.2, decay=0.5)
    other.load_state_dict(guard.state_dict())
    assert other.lr_scale == 0.125 and other.backtracks == 3


def test_rate_recovers_after_calm_epochs_and_never_exceeds_the_full_rate():
    x = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    opt = ClippedAdam([ParamSpec("x", x, 0.1)])
    guard = StepGuard(ratio=1.3, decay=0.5, recover_after=3)
    x.grad = torch.ones(1, dtype=torch.float64)
    guard.check(frames=2, loss=1.0, tensors={"x": x}, optimizer=opt)
    assert guard.check(frames=2, loss=2.0, tensors={"x": x}, optimizer=opt)        # a jump: rate halved
    assert guard.lr_scale == 0.5
    scales = []
    for loss in (0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3):                             # calm epochs
        guard.check(frames=2, loss=loss, tensors={"x": x}, optimizer=opt)
        scales.append(guard.lr_scale)
    assert scales == [0.5, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0]
    state = guard.state_dict()
    again = StepGuard(ratio=1.3, decay=0.5, recover_after=3)
    again.load_state_dict(state)
    assert again.lr_scale == 1.0 and again.calm == guard.calm


def test_without_recovery_a_cut_lasts():
    losses, guard = _run(StepGuard(ratio=1.3, decay=0.5, recover_after=0))
    assert guard.lr_scale == pytest.approx(0.5 ** guard.backtracks)
    _, recovering = _run(StepGuard(ratio=1.3, decay=0.5, recover_after=5))
    assert recovering.lr_scale > guard.lr_scale
