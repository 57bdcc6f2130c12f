"""The rollout's optional inputs: shapes checked with a message naming the input, rows cut to the frames used."""

import pytest
import torch

from saft.physics.rollout_inputs import anchor_inputs, drag_input, frame_rows

F64 = dict(dev="cpu", dt=torch.float64)


def test_frame_rows_cuts_to_the_transitions_used_and_names_a_wrong_shape():
    rows = torch.arange(5 * 2 * 3, dtype=torch.float32).reshape(5, 2, 3)
    got = frame_rows(rows, "a_vert", 4, (2, 3), **F64)
    assert got.dtype == torch.float64 and got.shape == (3, 2, 3) and torch.equal(got, rows[:3].double())
    assert frame_rows(None, "a_vert", 4, (2, 3), **F64) is None
    with pytest.raises(ValueError, match=r"a_vert must have shape \(>= 6, 2, 3\), got \(5, 2, 3\)"):
        frame_rows(rows, "a_vert", 7, (2, 3), **F64)
    with pytest.raises(ValueError, match="a_vert must have shape"):
        frame_rows(rows[:, :1], "a_vert", 4, (2, 3), **F64)


def test_anchor_inputs_default_to_x0_detached_and_check_shapes():
    x0 = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    assert anchor_inputs(None, None, x0, 4, **F64) == (None, None)
    w, at = anchor_inputs(torch.ones(4), None, x0, 4, **F64)
    assert w.dtype == torch.float64 and torch.equal(at, x0.detach()) and not at.requires_grad
    with pytest.raises(ValueError, match=r"anchor must have shape \(4,\)"):
        anchor_inputs(torch.ones(3), None, x0, 4, **F64)
    with pytest.raises(ValueError, match=r"anchor_positions must have shape \(4, 3\)"):
        anchor_inputs(torch.ones(4), torch.zeros(3, 3), x0, 4, **F64)


def test_drag_needs_triangles():
    assert drag_input(None, None, **F64) is None
    assert drag_input(0.5, torch.zeros(1, 3, dtype=torch.long), **F64).shape == ()
    with pytest.raises(ValueError, match="air drag needs the topology's triangles"):
        drag_input(0.5, None, **F64)
