"""The cloth's velocity at frame 0, learned (not in the paper, which starts the cloth at rest).

A video that starts mid-motion (a cloth already swinging or billowing) cannot be explained from rest: the
accelerations of the first frames would have to make up the missing momentum, and R_F and the schedule hold
them back. The shape phase can instead learn v0, parameterised as the per-frame accelerations are
(saft.reconstruct.force_field): an affine field over the template (12 numbers: a translation, a turn, a
swing about an edge) plus per-vertex velocities,

    v0(v) = u_v + c_0 + Σ_j x̂_v,j c_j

both starting at 0 (so a cloth at rest starts as before), each with its own Adam. R_V, the mean size of
v0 over the vertices, is its prior: at rest unless the video says otherwise.
"""

from __future__ import annotations

import torch

from saft.reconstruct.force_field import field_accelerations


def initial_velocity(vertex: torch.Tensor | None, field: torch.Tensor | None,
                     basis: torch.Tensor) -> torch.Tensor | None:
    """(V, 3) velocity at frame 0 from per-vertex velocities (V, 3) and affine coefficients (4, 3), either
    None when off; None when both are."""
    if vertex is None and field is None:
        return None
    v = field_accelerations(field[None], basis)[0] if field is not None else 0.0
    return v + vertex if vertex is not None else v


def velocity_prior(v0: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """R_V: mean over vertices of |v0| (m/s); 0 when v0 is not learned."""
    if v0 is None:
        return like.new_zeros(())
    return v0.norm(dim=-1).mean()


__all__ = ["initial_velocity", "velocity_prior"]
