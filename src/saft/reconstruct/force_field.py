"""A smooth, per-frame external acceleration field: affine in the template's coordinates.

The per-vertex accelerations D_f are 3V free numbers per frame, and Adam moves each by about one learning
rate per epoch whatever its gradient. A motion of the whole cloth (a translation, a swing about an edge,
a turn) needs the same acceleration, or one growing linearly across the cloth, at every vertex, and of
the size of gravity (~10 m/s²) where nothing is pinned: built from per-vertex steps of 0.2 m/s² it takes
tens of epochs per frame, and the schedule moves on long before (a held, swinging cloth without pins
was lost from frame ~6 on: BENCHMARKS.md). The field adds 12 numbers per frame,

    a_field(v, k) = c_k,0 + Σ_j x̂_v,j c_k,j      x̂_v: the template position, centred and scaled to [-1, 1]

which Adam moves as a whole. The simulation and R_F see the sum D_f + a_field (what acts on the cloth),
so this changes the parameterisation, not the model.
"""

from __future__ import annotations

import torch


def affine_basis(template: torch.Tensor) -> torch.Tensor:
    """(V, 4) basis [1, x̂, ŷ, ẑ] of the template: coordinates centred on the bounding box and divided by
    its largest half-extent (a flat template keeps a zero column)."""
    lo, hi = template.min(dim=0).values, template.max(dim=0).values
    half = ((hi - lo) / 2).max().clamp_min(1e-12)
    scaled = (template - (lo + hi) / 2) / half
    return torch.cat([torch.ones_like(scaled[:, :1]), scaled], dim=1)


def field_accelerations(coeffs: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """(F, 4, 3) coefficients, (V, 4) basis → (F, V, 3) accelerations."""
    return torch.einsum("vb,fbc->fvc", basis.to(coeffs), coeffs)


def total_accelerations(vertex_accel: torch.Tensor, field_coeffs: torch.Tensor | None,
                        basis: torch.Tensor) -> torch.Tensor:
    """What acts on the cloth beyond the constant acceleration: D_f (F, V, 3) plus the field when it is on
    (coefficients (F, 4, 3), or None)."""
    if field_coeffs is None:
        return vertex_accel
    return vertex_accel + field_accelerations(field_coeffs, basis)


__all__ = ["affine_basis", "field_accelerations", "total_accelerations"]
