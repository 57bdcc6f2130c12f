"""The shape phase's learned parameters (ShapeParams) and the stored frame states of windowed epochs (FrameStates).

Split from shape_phase.py, which optimizes them; see its docstring for what each parameter does in the loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from saft.reconstruct.force_field import total_accelerations
from saft.reconstruct.initial_velocity import initial_velocity


# the parameters that only some runs have, in the order params.tensors() lists them
OPTIONAL = ("field_accel", "light", "anchor_log10", "v0_field", "log10_drag")
# learned only with shape.optimize_stiffness; every other parameter is always learned
STIFFNESSES = ("log10_Y", "log10_B", "log10_S")


@dataclass
class ShapeParams:
    log10_Y: torch.Tensor
    log10_B: torch.Tensor
    log10_S: torch.Tensor
    const_accel: torch.Tensor      # (3,)
    vertex_accel: torch.Tensor     # (N-1, V, 3): during the substeps from frame k to k+1
    field_accel: torch.Tensor | None = None   # (N-1, 4, 3): the affine field's coefficients (force_field.py)
    light: torch.Tensor | None = None         # (3,): first-order light vector of the relative shading (render.shading)
    anchor_log10: torch.Tensor | None = None  # (V,): log10 of the soft anchors' stiffness per unit mass (s^-2)
    v0_field: torch.Tensor | None = None      # (4, 3): the affine velocity at frame 0 (initial_velocity.py)
    log10_drag: torch.Tensor | None = None    # 0-dim: log10 of the air drag coefficient (physics.air_drag > 0)

    def tensors(self) -> dict[str, torch.Tensor]:
        t = {"log10_Y": self.log10_Y, "log10_B": self.log10_B, "log10_S": self.log10_S,
             "const_accel": self.const_accel, "vertex_accel": self.vertex_accel}
        for name in OPTIONAL:
            if getattr(self, name) is not None:
                t[name] = getattr(self, name)
        return t

    def velocity(self, basis: torch.Tensor) -> torch.Tensor | None:   # (V, 3) at frame 0, or None (at rest)
        return initial_velocity(self.v0_field, basis)

    def accelerations(self, basis: torch.Tensor, lo: int, hi: int) -> torch.Tensor:
        """(hi - lo, V, 3) external accelerations beyond the constant one, frames lo..hi-1: D_f plus the
        affine field when it is on."""
        field = self.field_accel[lo:hi] if self.field_accel is not None else None
        return total_accelerations(self.vertex_accel[lo:hi], field, basis)


@dataclass
class FrameStates:
    """Detached positions and velocities at every frame boundary of the latest simulation that reached
    them: the start states of windowed epochs (shape.window > 0)."""

    x: torch.Tensor                # (N, V, 3)
    v: torch.Tensor                # (N, V, 3)
    frames: int = 1                # frames 0..frames-1 hold states
    fresh: int = 1                 # frames 0..fresh-1 hold the states of the current parameters

    def update(self, start: int, x: torch.Tensor, v: torch.Tensor) -> None:
        n = x.shape[0]
        self.x[start:start + n] = x.detach()
        self.v[start:start + n] = v.detach()
        self.frames = max(self.frames, start + n)
        if start < self.fresh:
            self.fresh = max(self.fresh, start + n)

    def stepped(self, first_changed: int) -> None:
        """The optimizer changed the accelerations from frame `first_changed` on (0: every parameter): the
        states after that frame no longer match the parameters."""
        self.fresh = min(self.fresh, first_changed + 1)


__all__ = ["FrameStates", "ShapeParams"]
