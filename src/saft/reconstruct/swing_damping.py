"""The velocity damping, lowered by a trial where the clip swings under gravity (issue 29; not in the paper).

saft damps every velocity by v <- d v before each substep (physics.damping, the paper's 0.9). That is an
"ether" damping: it brakes the cloth's whole motion, not only its deformation. With d = 0.9 and 4 substeps
of 1/120 s, a cloth falling under gravity alone reaches d g h / (1 - d) = 0.74 m/s and no more, while a
cloth held at one corner swings at 1.6 m/s (the one-corner scenes, saft's own twin as Newton's): the
external accelerations must then push the swing on at about (1 - d) / h · v = 19 m/s² (twice gravity)
against R_F and the schedule, and the optimiser does not get there. The model-matched twin with its own
stiffnesses and wind but saft's damping is 161 (1e-4 m², vertex MSE) from the truth; with 0.99, 2.5.

A real cloth that is driven by wind (the demo, R1, the gusts) wants the paper's damping (0.97 made R1 2.4x
worse; BENCHMARKS.md, "Relative shading in the shape renderer; damping"). What tells a swing is the trial
below: before the first epoch, the cloth is simulated from rest with the initial parameters (gravity, no
learned forces) through the first TRIAL_FRAMES frames under each damping, projected, and compared with the
point tracks. Where the swing under gravity explains the tracks much better with the low damping (its
residual at most GATE x the default's), the run uses physics.swing_damping, and the accelerations' learning
rates are scaled by rate_scale; elsewhere (the cloth does not move from rest, or moves the same under both)
the default, and the run is bit for bit the option's off.
"""

from __future__ import annotations

import logging

import torch

from saft.reconstruct.tracks import VertexTracks, project
from saft.scene.camera import Camera

log = logging.getLogger("saft")

TRIAL_FRAMES = 10     # frames simulated from rest by the trial (1/3 s at 30 fps)
GATE = 0.5            # the low damping is used where its residual is at most this share of the default's
# A held acceleration a brings the cloth to the velocity d h a / (1 - d): 10x more with 0.99 than with 0.9.
# The learning rates of the accelerations, tuned for the paper's damping, are scaled by rate_scale (the ratio
# of 1 - d) where the low damping is used: unscaled, they overshot (the step guard cut them 1-2 times) and
# the Newton one-corner scene went 24.0 -> 32.4; x0.25: 27.5, x0.1: 12.0 (BENCHMARKS.md, "The one-corner
# scene: the damping brakes the swing").
FORCE_RATES = ("const_accel", "vertex_accel", "field_accel")


def rate_scale(default: float, low: float) -> float:
    """(1 - low) / (1 - default): the accelerations' learning-rate factor under `low`, about the ratio of the
    velocities a held acceleration reaches under `default` and under `low`."""
    return (1.0 - low) / (1.0 - default)


def track_residual(positions: torch.Tensor, tracks: VertexTracks, camera: Camera) -> float:
    """Mean distance in pixels of the projected vertices (F, V, 3) (frames 0..F-1) to their valid tracks."""
    valid = tracks.valid[: positions.shape[0]].to(positions.device)
    if not bool(valid.any()):
        return float("nan")
    uv, _ = project(positions, camera)
    return float((uv - tracks.points[: positions.shape[0]].to(uv)).norm(dim=-1)[valid].mean())


def damping_residuals(simulate, dampings: list[float], tracks: VertexTracks, camera: Camera,
                      frames: int) -> list[float]:
    """The trial: simulate(d, frames) -> (frames, V, 3) positions from rest under damping d; each one's
    track_residual."""
    with torch.no_grad():
        return [track_residual(simulate(d, frames), tracks, camera) for d in dampings]


def choose_damping(sim, params, tracks: VertexTracks | None, camera: Camera, default: float, low: float) -> float:
    """The damping of the run: `low` where the trial's residual with it is at most GATE x that with `default`,
    else `default` (also without tracks, or with low <= 0: the option off). `sim`: ShapeSimulator (its
    damping is left at `default`), `params`: ShapeParams before the first epoch (saft.reconstruct.shape_phase,
    which imports this module)."""
    if low <= 0 or tracks is None or tracks.points.shape[0] < 3:
        return default
    frames = min(TRIAL_FRAMES, tracks.points.shape[0])

    def simulate(d: float, n: int) -> torch.Tensor:
        sim.damping = d
        return sim.simulate(params, n)

    try:
        r_default, r_low = damping_residuals(simulate, [default, low], tracks, camera, frames)
    finally:
        sim.damping = default
    chosen = low if r_low <= GATE * r_default else default
    log.info("damping %.4g: from rest under gravity over %d frames the tracks are %.2f px off with %.4g, %.2f px "
             "with %.4g (gate %.2f)", chosen, frames, r_default, default, r_low, low, GATE)
    return chosen


def run_damping(state, sim, tracks: VertexTracks | None, camera: Camera, phys) -> float:
    """The run's damping: a resumed run's (state.damping, from its checkpoint) or choose_damping's from
    physics.damping and physics.swing_damping (`phys`: PhysicsConfig), replaced by physics.swing_run_damping
    where the trial picks the low one and that option is on (> 0). Where it is not the default, the learning
    rates of the accelerations (FORCE_RATES) are scaled by rate_scale in state.optimizer, built afresh at every
    start of the phase (`state`: ShapeState before its first epoch of this process)."""
    chosen = state.damping
    if chosen is None:
        chosen = choose_damping(sim, state.params, tracks, camera, phys.damping, phys.swing_damping)
        if chosen != phys.damping and phys.swing_run_damping > 0:   # the trial's pick, run lower still
            log.info("damping %.4g in the run (physics.swing_run_damping)", phys.swing_run_damping)
            chosen = phys.swing_run_damping
    if chosen != phys.damping:
        for name in FORCE_RATES:
            if name in state.optimizer.specs:
                state.optimizer.specs[name].lr *= rate_scale(phys.damping, chosen)
    return chosen


__all__ = ["FORCE_RATES", "GATE", "TRIAL_FRAMES", "choose_damping", "damping_residuals", "rate_scale", "run_damping",
           "track_residual"]
