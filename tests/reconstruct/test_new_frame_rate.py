"""A backtrack's rate cut kept to the frames it was made on (saft.reconstruct.new_frame_rate)."""

from types import SimpleNamespace

import torch

from saft.reconstruct.optim import ClippedAdam, ParamSpec
from saft.reconstruct.step_guard import StepGuard
from saft.reconstruct.new_frame_rate import row_boost, step


def test_on_by_default():
    from saft.reconstruct.config import ShapeConfig
    assert ShapeConfig().backtrack_new_frames is True


def test_boost_is_none_while_every_row_in_use_carries_the_same_cuts():
    guard = StepGuard(ratio=1.3, decay=0.5)
    assert row_boost(guard, frames=10, rows=31) is None              # no cut yet
    guard.cut_frames = [32]
    assert row_boost(guard, frames=32, rows=31) is None              # a cut with every frame in use
    guard.cut_frames = [9]
    assert row_boost(guard, frames=9, rows=31) is None               # the frames of the cut, none added since
    recovering = StepGuard(ratio=1.3, decay=0.5, recover_after=10)
    recovering.cut_frames = [9]
    assert row_boost(recovering, frames=20, rows=31) is None         # its cuts do not last: nothing to keep


def test_rows_added_after_a_cut_are_stepped_without_it():
    guard = StepGuard(ratio=1.3, decay=0.5)
    guard.cut_frames = [9]                                           # 9 frames in use: transitions 0..7
    b = row_boost(guard, frames=12, rows=31)
    assert b.tolist() == [1.0] * 8 + [2.0] * 23
    guard.cut_frames = [9, 20]                                       # a second cut covers rows 0..18
    b = row_boost(guard, frames=25, rows=31)
    assert b.tolist() == [1.0] * 8 + [2.0] * 11 + [4.0] * 12


def test_guard_records_the_frames_of_each_cut_and_checkpoints_them():
    x = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    opt = ClippedAdam([ParamSpec("x", x, 0.1)])
    guard = StepGuard(ratio=1.5, decay=0.5)
    x.grad = torch.ones(1, dtype=torch.float64)
    guard.check(frames=7, loss=1.0, tensors={"x": x}, optimizer=opt)
    assert guard.check(frames=7, loss=2.0, tensors={"x": x}, optimizer=opt)
    assert guard.cut_frames == [7]
    again = StepGuard(ratio=1.5, decay=0.5)
    again.load_state_dict(guard.state_dict())
    assert again.cut_frames == [7] and again.lr_scale == 0.5
    older = StepGuard(ratio=1.5, decay=0.5)
    older.load_state_dict({"lr_scale": 0.5, "backtracks": 1, "calm": 0})   # a checkpoint from before the option
    assert older.cut_frames == []


def _params(seed: int):
    g = torch.Generator().manual_seed(seed)
    va = torch.randn(5, 4, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    fa = torch.randn(5, 4, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    c = torch.randn(3, generator=g, dtype=torch.float64).requires_grad_(True)
    return SimpleNamespace(vertex_accel=va, field_accel=fa, const_accel=c)


def _grads(p, seed: int):
    g = torch.Generator().manual_seed(100 + seed)
    for t in (p.vertex_accel, p.field_accel, p.const_accel):
        t.grad = torch.randn(t.shape, generator=g, dtype=torch.float64)


def _opt(p, lr_rows: float = 0.2):
    return ClippedAdam([ParamSpec("vertex_accel", p.vertex_accel, lr_rows),
                        ParamSpec("field_accel", p.field_accel, 0.3),
                        ParamSpec("const_accel", p.const_accel, 0.1)], clip=1e9, quantile=1.0)


def test_usual_step_bit_for_bit_where_off_or_no_row_differs():
    for on, cuts in ((False, [3]), (True, []), (True, [6])):
        a, b = _params(0), _params(0)
        oa, ob = _opt(a), _opt(b)
        guard = StepGuard(ratio=1.3, decay=0.5)
        guard.cut_frames = cuts
        for k in range(3):
            _grads(a, k), _grads(b, k)
            oa.step()
            step(ob, b, guard, frames=6, on=on)
        for n in ("vertex_accel", "field_accel", "const_accel"):
            assert torch.equal(getattr(a, n), getattr(b, n))


def test_a_boosted_row_moves_as_adam_at_the_boosted_rate():
    guard = StepGuard(ratio=1.3, decay=0.5)
    guard.cut_frames = [3]                      # rows 0, 1 cut; rows 2.. added after the cut
    p, ref_cut, ref_full = _params(1), _params(1), _params(1)
    o = _opt(p)
    o_cut, o_full = _opt(ref_cut), _opt(ref_full)
    for o_ in (o, o_cut):
        o_.set_lr_factor(0.5)                   # the guard's global cut
    for k in range(2):
        for q in (p, ref_cut, ref_full):
            _grads(q, k)
        step(o, p, guard, frames=6, on=True)
        o_cut.step()
        o_full.step()
    assert torch.allclose(p.vertex_accel[:2], ref_cut.vertex_accel[:2])
    assert torch.allclose(p.vertex_accel[2:], ref_full.vertex_accel[2:])
    assert torch.allclose(p.field_accel[2:], ref_full.field_accel[2:])
    assert torch.equal(p.const_accel, ref_cut.const_accel)         # shared parameters keep the global cut
