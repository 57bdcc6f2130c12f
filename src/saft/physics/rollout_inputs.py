"""The rollout's optional per-frame and per-vertex inputs, checked and put on the topology's device.

Split from simulation.py (which runs the rollout) so that each input's shape rule sits in one place.
"""

from __future__ import annotations

import torch


def frame_rows(value, name: str, num_frames: int, row_shape: tuple, dev, dt) -> torch.Tensor | None:
    """A tensor of one row per frame transition, (>= num_frames - 1, *row_shape), cut to num_frames - 1 rows
    (longer is fine: frames are added progressively, the unused rows get zero gradient); None stays None."""
    if value is None:
        return None
    value = torch.as_tensor(value).to(device=dev, dtype=dt)
    if value.dim() != 1 + len(row_shape) or value.shape[0] < num_frames - 1 or tuple(value.shape[1:]) != row_shape:
        want = ", ".join(str(s) for s in row_shape)
        raise ValueError(f"{name} must have shape (>= {num_frames - 1}, {want}), got {tuple(value.shape)}")
    return value[: num_frames - 1]


def anchor_inputs(anchor, anchor_positions, x0: torch.Tensor, num_vertices: int, dev, dt):
    """(anchor (V,), anchor_positions (V, 3) detached, x0 where not given), or (None, None) without anchors."""
    if anchor is None:
        return None, None
    anchor = torch.as_tensor(anchor).to(device=dev, dtype=dt)
    if anchor.shape != (num_vertices,):
        raise ValueError(f"anchor must have shape ({num_vertices},), got {tuple(anchor.shape)}")
    at = x0 if anchor_positions is None else torch.as_tensor(anchor_positions).to(device=dev, dtype=dt)
    if at.shape != (num_vertices, 3):
        raise ValueError(f"anchor_positions must have shape ({num_vertices}, 3), got {tuple(at.shape)}")
    return anchor, at.detach()


def drag_input(l_drag, triangles, dev, dt) -> torch.Tensor | None:
    """log10 c as a 0-dim tensor, or None without drag."""
    if l_drag is None:
        return None
    if triangles is None:
        raise ValueError("air drag needs the topology's triangles (ClothTopology.from_quads)")
    return torch.as_tensor(l_drag).to(device=dev, dtype=dt).reshape(())


__all__ = ["anchor_inputs", "drag_input", "frame_rows"]
