"""The cloth's velocity at frame 0, learned (not in the paper, which starts the cloth at rest).

A video that starts mid-motion (a cloth already swinging or billowing) cannot be explained from rest: the
accelerations of the first frames would have to make up the missing momentum, and R_F and the schedule hold
them back. With shape.lr_v0 > 0 the shape phase learns v0 as an affine field over the template, as the
per-frame accelerations have one (saft.reconstruct.force_field; 12 numbers: a translation, a turn, a swing
about an edge),

    v0(v) = c_0 + Σ_j x̂_v,j c_j

started from the point tracks' first step (field_from_tracks: the least-squares affine velocity whose image
motion over frame 0 → 1 is the tracks', ridge-regularised so that what the image cannot see, motion along
the rays, stays near 0; a cloth at rest starts near rest) and learned by its own Adam. R_V, the mean size of
v0 over the vertices, is its prior: at rest unless the video says otherwise. Per-vertex velocities besides
the field lost (BENCHMARKS.md, "A clip that starts mid-motion").
"""

from __future__ import annotations

import torch

from saft.reconstruct.force_field import field_accelerations
from saft.reconstruct.tracks import VertexTracks, project
from saft.scene.camera import Camera


def initial_velocity(field: torch.Tensor | None, basis: torch.Tensor) -> torch.Tensor | None:
    """(V, 3) velocity at frame 0 from the affine coefficients (4, 3); None when off (at rest)."""
    return None if field is None else field_accelerations(field[None], basis)[0]


def velocity_prior(v0: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """R_V: mean over vertices of |v0| (m/s); 0 when v0 is not learned."""
    if v0 is None:
        return like.new_zeros(())
    return v0.norm(dim=-1).mean()


def field_from_tracks(tracks: VertexTracks, template: torch.Tensor, camera: Camera, frame_dt: float,
                      basis: torch.Tensor, ridge: float = 1e-2) -> torch.Tensor | None:
    """(4, 3) affine coefficients of the velocity at frame 0 whose projected motion over one frame best
    matches the tracks' step from frame 0 to 1, linearised at the template: min Σ_v |J_v v0(v) dt − Δp_v|²
    + ridge · tr(AᵀA)/12 · |c|², J_v the projection's Jacobian (2 × 3, by finite differences). None with
    fewer than 8 tracks valid in both frames."""
    if tracks.points.shape[0] < 2:
        return None
    valid = (tracks.valid[0] & tracks.valid[1]).to(template.device)
    if int(valid.sum()) < 8:
        return None
    x = template.detach()[valid].to(torch.float64)
    b = basis[valid].to(torch.float64)
    uv0, _ = project(x, camera)
    step = tracks.points[1].to(x)[valid] - uv0                              # (n, 2) pixels
    eps = 1e-5
    jac = torch.stack([(project(x + eps * e, camera)[0] - uv0) / eps
                       for e in torch.eye(3, dtype=x.dtype, device=x.device)], dim=-1)   # (n, 2, 3)
    a = (frame_dt * jac[:, :, None, :] * b[:, None, :, None]).reshape(-1, 12)  # column k = 3 j + c: c_{j,c}
    ata = a.T @ a
    ata = ata + ridge * torch.trace(ata) / 12 * torch.eye(12, dtype=x.dtype, device=x.device)
    return torch.linalg.solve(ata, a.T @ step.reshape(-1)).reshape(4, 3).to(template.dtype)


def seed_field_from_tracks(field: torch.Tensor, tracks: VertexTracks, template: torch.Tensor, camera: Camera,
                           frame_dt: float, basis: torch.Tensor) -> None:
    """Set the affine coefficients `field` (4, 3) in place to field_from_tracks's, where there are enough tracks."""
    start = field_from_tracks(tracks, template, camera, frame_dt, basis)
    if start is not None:
        with torch.no_grad():
            field.copy_(start)


__all__ = ["field_from_tracks", "seed_field_from_tracks", "initial_velocity", "velocity_prior"]
