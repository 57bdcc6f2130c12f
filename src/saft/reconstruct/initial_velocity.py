"""The cloth's velocity at frame 0, learned (not in the paper, which starts the cloth at rest).

A video that starts mid-motion (a cloth already swinging or billowing) cannot be explained from rest: the
accelerations of the first frames would have to make up the missing momentum, and R_F and the schedule hold
them back. With shape.lr_v0 > 0 the shape phase learns v0 as an affine field over the template, as the
per-frame accelerations have one (saft.reconstruct.force_field; 12 numbers: a translation, a turn, a swing
about an edge),

    v0(v) = c_0 + Σ_j x̂_v,j c_j

started from the point tracks' first step beyond what the physics from rest gives (start_motion: the
least-squares affine velocity whose image motion over frame 0 → 1 is the tracks' less that of frame 1
simulated with v0 = 0, ridge-regularised so that what the image cannot see, motion along the rays, stays
near 0) and learned by its own Adam. R_V, the mean size of v0 over the vertices, is its prior.

Only where the clip starts moving (StartMotion.moving; else v0 is dropped and the run is the lr_v0 = 0
run): learned from a small start, v0 drifts along the rays and trades with the accelerations (the demo,
which starts at rest: seed 0.008 m/s, learned 0.06-0.09 m/s mostly in depth, and the first Adam step of
0.02 per coefficient made the step guard halve every rate twice; CD2 0.347 -> 0.483). A significance test
alone does not tell such a clip: the demo's first step (0.06 px) is 3.7x the tracks' noise. What tells it
is the size of that step against the clip's own motion (0.11 of its median step). Per-vertex velocities
besides the field lost (BENCHMARKS.md, "A clip that starts mid-motion", "Learn v0 only where the clip
starts moving").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from saft.reconstruct.force_field import field_accelerations
from saft.reconstruct.optim import ClippedAdam
from saft.reconstruct.tracks import VertexTracks, project
from saft.scene.camera import Camera

log = logging.getLogger("saft")


def initial_velocity(field: torch.Tensor | None, basis: torch.Tensor) -> torch.Tensor | None:
    """(V, 3) velocity at frame 0 from the affine coefficients (4, 3); None when off (at rest)."""
    return None if field is None else field_accelerations(field[None], basis)[0]


def velocity_prior(v0: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """R_V: mean over vertices of |v0| (m/s); 0 when v0 is not learned."""
    if v0 is None:
        return like.new_zeros(())
    return v0.norm(dim=-1).mean()


@dataclass
class StartMotion:
    """The tracks' step from frame 0 to 1 beyond what the physics from rest gives, and the affine velocity
    that explains it (image motions: mean over the tracks, pixels per frame)."""

    field: torch.Tensor    # (4, 3) affine coefficients of v0
    fitted_px: float       # the field's image motion over one frame
    rest_px: float         # what the field leaves of the step: the tracks' noise and non-affine motion
    median_px: float       # the clip's typical motion: median over the frames of the tracks' mean step

    @property
    def moving(self) -> bool:
        """Whether the clip starts in motion: the field's motion is a real share of the clip's and above the
        tracks' noise (MIN_SHARE, MIN_SNR)."""
        return self.fitted_px >= MIN_SHARE * self.median_px and self.fitted_px >= MIN_SNR * self.rest_px


# The gate, from 15 scenes (BENCHMARKS.md, "Learn v0 only where the clip starts moving"): fitted / median is
# 0.49-3.5 on the three independent scenes cut mid-motion, 0.04-0.46 on those that start at rest with the
# physics (the demo 0.12, R1 0.24, the saft-simulated twins 0.04-0.46, Newton's drops 0.07-0.17);
# fitted / rest 3.0-4.6 mid-motion, 0.5-2.1 on the twins and drops. Newton's gust, side gust and fold
# (0.98-1.97, 7.9-8.1) do move in their first frame: their 40 x 40 frame 0 is not the template at rest.
MIN_SHARE = 0.3
MIN_SNR = 2.5


def _mean_norm(step: torch.Tensor) -> float:
    return float(step.reshape(-1, 2).norm(dim=-1).mean())


def start_motion(tracks: VertexTracks, template: torch.Tensor, camera: Camera, frame_dt: float,
                 basis: torch.Tensor, from_rest: torch.Tensor | None = None, ridge: float = 1e-2) -> StartMotion | None:
    """The affine velocity at frame 0 whose projected motion over one frame best matches the tracks' step
    from frame 0 to 1 less the step `from_rest` gives ((V, 3) frame 1 simulated from rest: what gravity and
    the template's own forces do; None: the template), linearised at the template: min Σ_v |J_v v0(v) dt −
    Δp_v|² + ridge · tr(AᵀA)/12 · |c|², J_v the projection's Jacobian (2 × 3, by finite differences). None
    with fewer than 8 tracks valid in both frames."""
    if tracks.points.shape[0] < 2:
        return None
    valid = (tracks.valid[0] & tracks.valid[1]).to(template.device)
    if int(valid.sum()) < 8:
        return None
    x = template.detach()[valid].to(torch.float64)
    b = basis[valid].to(torch.float64)
    uv0, _ = project(x, camera)
    rest = uv0 if from_rest is None else project(from_rest.detach()[valid].to(x), camera)[0]
    step = tracks.points[1].to(x)[valid] - rest                             # (n, 2) pixels
    eps = 1e-5
    jac = torch.stack([(project(x + eps * e, camera)[0] - uv0) / eps
                       for e in torch.eye(3, dtype=x.dtype, device=x.device)], dim=-1)   # (n, 2, 3)
    a = (frame_dt * jac[:, :, None, :] * b[:, None, :, None]).reshape(-1, 12)  # column k = 3 j + c: c_{j,c}
    ata = a.T @ a
    ata = ata + ridge * torch.trace(ata) / 12 * torch.eye(12, dtype=x.dtype, device=x.device)
    c = torch.linalg.solve(ata, a.T @ step.reshape(-1))
    steps = [tracks.points[k + 1][both] - tracks.points[k][both]
             for k in range(tracks.points.shape[0] - 1) if (both := tracks.valid[k] & tracks.valid[k + 1]).any()]
    median = float(torch.tensor([_mean_norm(d) for d in steps]).median())
    return StartMotion(c.reshape(4, 3).to(template.dtype), _mean_norm(a @ c), _mean_norm(step.reshape(-1) - a @ c),
                       median)


def start_velocity(params, optimizer: ClippedAdam, sim, tracks: VertexTracks | None, camera: Camera) -> StartMotion | None:
    """Before the shape phase's first epoch (v0 and the accelerations still 0): v0 := start_motion's field
    when the clip starts in motion and no soft anchors hold it; otherwise (or without tracks) v0 is dropped,
    params.v0_field = None and out of the optimizer, and the phase runs as with shape.lr_v0 = 0. The anchors
    hold the cloth where it hangs at rest, the template, which a start in motion contradicts (Newton's
    unpinned gust, whose first step the gate reads as motion: CD2 1.28 with v0 dropped, 17.5 learned).
    `params`: ShapeParams, `sim`: ShapeSimulator (saft.reconstruct.shape_phase, which imports this module)."""
    motion = None
    if tracks is not None and tracks.points.shape[0] >= 2:
        with torch.no_grad():
            from_rest = sim.simulate(params, 2)[1]
        motion = start_motion(tracks, sim.template, camera, sim.frame_dt, sim.field_basis, from_rest)
    anchored = params.anchor_log10 is not None
    learned = motion is not None and motion.moving and not anchored
    if learned:
        with torch.no_grad():
            params.v0_field.copy_(motion.field)
    else:
        params.v0_field = None
        optimizer.drop("v0_field")
    if motion is not None:
        verdict = ("learned" if learned else "0 (soft anchors: the cloth hangs at rest)" if anchored
                   else "0 (the clip starts at rest)")
        log.info("v0 %s: the first step's affine motion %.3f px (%.2f of the median step %.3f px, %.1f x the "
                 "rest %.3f px)", verdict, motion.fitted_px,
                 motion.fitted_px / max(motion.median_px, 1e-12), motion.median_px,
                 motion.fitted_px / max(motion.rest_px, 1e-12), motion.rest_px)
    return motion


__all__ = ["MIN_SHARE", "MIN_SNR", "StartMotion", "initial_velocity", "start_motion",
           "start_velocity", "velocity_prior"]
