"""Every hyperparameter of a reconstruction, in one typed config with the published method's defaults.

Defaults come from ../shared/REFERENCE.md (the authors' code where it differs from the paper). The config
is saved as DIR/config.toml beside every result; `--config FILE.toml` and `--set key=value` override it,
and unknown keys or wrong types are rejected (saft.config_io).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from saft.appearance.config import AppearanceConfig, cpu_profile, cuda_profile
from saft.config_io import from_dict, load_toml, merge_overrides, to_dict
from saft.device import appearance_device
from saft.physics import (DEFAULT_DAMPING, DEFAULT_DENSITY, DEFAULT_LOG10_B, DEFAULT_LOG10_S, DEFAULT_LOG10_Y,
                          DEFAULT_SUBSTEPS, LOG10_LIMITS)
from saft.reconstruct.config_checks import check_config_ranges


@dataclass
class RunConfig:
    device: Literal["auto", "cpu", "cuda"] = "auto"
    seed: int = 0
    threads: int = 0                      # torch CPU threads; 0 = automatic
    # shape phase: frames rendered side by side (saft.reconstruct.frame_renders); 0 = automatic (CPU: the cores, ≤ 4)
    render_threads: int = 0
    checkpoint_seconds: float = 20.0      # write the resume state at most this often (and at phase ends)


@dataclass
class RenderConfig:
    backend: Literal["auto", "torch", "nvdiffrast"] = "auto"
    scale: float = 1.0                    # working image = crop resized by this factor (1 = native, as the paper)


@dataclass
class TextureConfig:
    """Phase 1: a texture fitted on frame 0 with the template geometry."""

    enabled: bool = True
    epochs: int = 200
    size: int = 512                       # texture is size × size texels
    init_value: float = 0.5
    init_from_scene: bool = True          # start from the scene's texture.png when it has one
    lr: float = 5e-2
    lambda_smooth: float = 1e-4           # λ_T · FD(T)


@dataclass
class PhysicsConfig:
    """Simulation settings of phase 2; defaults and stiffness ranges are saft.physics's (one copy)."""

    substeps: int = DEFAULT_SUBSTEPS      # simulation steps per video frame (h = frame_dt / substeps)
    density: float = DEFAULT_DENSITY      # kg/m² (areal density; only the ratio force/mass matters)
    damping: float = DEFAULT_DAMPING      # velocity factor applied before each substep
    # Element Hessians in the implicit step: "projected" (each clamped to PSD: the system is always positive
    # definite) or "exact" (the reference's; may be indefinite when the cloth is compressed).
    hessian: Literal["projected", "exact"] = "projected"
    # The shape the cloth springs back to: "template" (the rest angles are the template's own hinge angles)
    # or "flat" (the template flattened: each hinge's edges projected on the tangent plane at its vertex, so
    # a billowed frame 0 of a clip that starts mid-motion is not taken as the cloth's rest shape; woven cloth
    # is flat at rest), or "moving" (flat when the clip starts in motion, i.e. when shape.lr_v0's gate learns
    # v0 with either rest shape, else the template). Rest lengths are the template's edge lengths either way.
    # "moving" (issue 29, BENCHMARKS "The rest shape flat where the clip starts moving"): Newton from frame 8
    # gust 5.76 -> 1.64, corners 1.39 -> 1.14, unpinned gust 53.4 -> 47.2, fold 2.31 -> 2.78 (medians); where
    # the gate drops v0 (demo, R1, the curved appearance clips) the run is the template's, bit for bit.
    rest_shape: Literal["template", "flat", "moving"] = "moving"
    # The damping used instead of `damping` where the clip swings under gravity (0 = off): before the first
    # epoch the cloth is simulated from rest (gravity, no learned forces) under both and compared with the
    # point tracks; where this one's residual is at most half the default's, the run uses it
    # (saft.reconstruct.swing_damping), with the accelerations' learning rates scaled by (1 - this) / (1 -
    # damping). The paper's 0.9 brakes a falling cloth at 0.74 m/s (4 substeps at 30 fps); a cloth held at one
    # corner swings at 1.6 m/s. 0.99: one corner pinned, twin 10.75 -> 2.33, Newton 24.0 -> 12.0; the trial
    # keeps the default on the other pinned independent scenes, the appearance clips, R1 and the demo (BENCHMARKS.md,
    # "The one-corner scene: the damping brakes the swing"). The default since 2026-11-27.
    swing_damping: float = 0.99
    # The damping the run uses where the trial above picked swing_damping (0 = swing_damping itself, the
    # option off). The trial still compares `damping` with swing_damping, so where it keeps `damping` the run
    # is unchanged, bit for bit; only the swinging runs change. The accelerations' rates are scaled by (1 -
    # this) / (1 - damping). Why: saft's rollout of the Newton one-corner cloth with the aerodynamic
    # accelerations it felt (no learned force) is 49.5 from the truth (vertex MSE, 1e-4 m^2) at 0.99, 37.5 at
    # 0.995, 31.5 at 0.999: the ether damping still brakes Newton's swing, whose braking is the air's (now
    # physics.air_drag). 0.995 with shape.swing_lambda_sil 1.0: Newton one corner 9.94 -> 6.35, its twin 2.58 ->
    # 1.77 (BENCHMARKS.md "The swinging cloth: the accelerations' rate and the silhouette weight"; the gain
    # is the rates' 0.05 more than the damping: 0.99 with the rates halved 8.51). The default since 2026-11-27
    # with swing_lambda_sil 1.0 (seed 1: 9.71 -> 6.36, twin 2.51 -> 1.86; chosen on seed 0 of the Newton scene).
    swing_run_damping: float = 0.995
    # Air drag of still air on the cloth (saft.physics.drag; issue 29, not in the paper): the initial coefficient
    # c = rho_air C_d / 2 in kg/m^3 of the pressure -c A |u| u n on each triangle (0 = off). The prior for a
    # flat plate broadside is ~0.6 (rho_air 1.2, C_d 1); c is then learned in log10 (shape.lr_air_drag) within
    # air_drag_range. Only c / density matters, like the stiffnesses. 0.6, kept where air_drag_where says, is the
    # default since 2026-11-27 (Newton one corner 12.35 -> 9.94 and 12.26 -> 9.71, seeds 0 / 1; its twin 2.39 ->
    # 2.58 and 2.35 -> 2.51; everywhere else the run is bit for bit the one without: BENCHMARKS.md "Air drag").
    air_drag: float = 0.6
    air_drag_range: tuple[float, float] = (0.01, 5.0)
    # Where the drag is kept (saft.reconstruct.air_drag): "swing" only where the swing trial picks
    # swing_damping (a cloth swinging from one corner: Newton one corner 12.35 -> 9.94), "always" everywhere
    # (the wind-driven Newton scenes lost: gust 1.13 -> 2.86, fold +16 %).
    air_drag_where: Literal["swing", "always"] = "swing"
    log10_Y_init: float = DEFAULT_LOG10_Y
    log10_B_init: float = DEFAULT_LOG10_B
    log10_S_init: float = DEFAULT_LOG10_S
    log10_Y_range: tuple[float, float] = LOG10_LIMITS["log10_Y"]
    log10_B_range: tuple[float, float] = LOG10_LIMITS["log10_B"]
    log10_S_range: tuple[float, float] = LOG10_LIMITS["log10_S"]


@dataclass
class ShapeConfig:
    """Phase 2: physics-based shape from template (paper section 3.3.2)."""

    enabled: bool = True
    initial_frames: int = 3               # frames 0..2 first
    initial_epochs: int = 0               # epochs on the initial frames (0 = add_frame_every)
    add_frame_every: int = 5              # one more frame every 5 epochs
    # Then this many epochs with all frames. The reference runs 24 (its 260-epoch schedule for 50 frames).
    # 24 -> 36 -> 72 each measured better on R1 (perturbed runs) and on all six benchmark scenes, the last
    # frames most; 72 costs R1 about 15 % more time than 36 (BENCHMARKS.md, "72 final epochs").
    final_epochs: int = 72
    # Convergence-driven schedule (saft.reconstruct.frame_schedule; 0 = the fixed schedule, the paper): after
    # add_frame_every epochs, the newest frame waits while the loss still falls by more than plateau_tol
    # (relative, lowest of the last two epochs against the lowest before), up to this many extra epochs.
    plateau_max_extra: int = 0
    plateau_tol: float = 0.02
    # Windowed epochs (0 = off: every epoch simulates from the template, as the paper): while frames are
    # added, simulate only the newest `window` frames from the stored state before them (the accelerations
    # before the window held), with a full pass every `full_pass_every` epochs and in the final epochs.
    # The work per added frame is then bounded (long videos), and on R1 the result is better than with
    # full passes (median CD2 of 3 runs 0.47-0.53 against 0.94; BENCHMARKS.md). 16, not 8: a window of 8 was 1.3-4.9x
    # worse on the fast benchmark scenes, 16 is within their run-to-run noise of full passes.
    window: int = 16
    full_pass_every: int = 25
    lambda_image: float = 1.0
    lambda_sil: float = 0.2
    # lambda_sil in a run where the swing trial picks physics.swing_damping (0 = off: lambda_sil there too;
    # saft.reconstruct.swing_weights). Every other run keeps lambda_sil, bit for bit. Newton one corner,
    # with physics.swing_run_damping 0.995: 8.31 -> 6.34 at 1.0; ALONE (damping 0.99, the rates x0.1) it
    # loses: 9.94 -> 15.95 (BENCHMARKS.md, "The swinging cloth…"): the two are defaults together.
    swing_lambda_sil: float = 1.0
    # A silhouette pull that grows with the gap, in scenes with pinned vertices only (saft.reconstruct.
    # silhouette_reach; 0 = off, the plain coverage MSE): each pixel of the observed mask weighs
    # 1 + sil_reach_gain * (min(d, r) / r)^2 in the silhouette term, d its distance in pixels to the mask's
    # border, r = sil_reach_px; so a rendered edge that stops short of the mask is pulled out harder the
    # farther it is. The pins hold the depth that such a pull otherwise trades for nearness: without pins
    # (r 24, gain 16) R1 0.446 -> 0.486 (median of 3 perturbed runs) and the unpinned Newton gust +11 %,
    # so an unpinned scene keeps the plain term. Pinned, one run each: Newton flag 18.99 -> 13.91, side gust
    # 22.34 -> 20.99, gust 1.157 -> 1.124, fold 1.140 -> 1.114, corners +2 %, one corner +0.6 %, demo level
    # (BENCHMARKS.md, "A silhouette pull with reach at the border"); with backtrack_new_frames the Newton
    # appearance clips cotton 47.40 -> 13.20, satin 20.97 -> 8.48, plaid 5.18 -> 4.67 (fifteenth session).
    sil_reach_px: float = 24.0
    sil_reach_gain: float = 16.0
    lambda_energy: float = 2.0            # R_E, stiffnesses detached
    lambda_force: float = 2e-4            # R_F
    force_directions: Literal["current", "template"] = "current"  # viewing directions for R_F
    # What R_F penalises: "vertex" = the per-vertex accelerations D_f alone; "total" = C + D_f, the total
    # external acceleration (the paper's supplement and the reference's code).
    force_target: Literal["vertex", "total"] = "vertex"
    # Weight of the force's component along the viewing ray in R_F (0 = the paper: only the part
    # perpendicular to the ray is penalised; 1 = the whole vector), in scenes with nothing pinned and in
    # scenes with pinned vertices. Without pins nothing else holds the cloth's depth: with the affine field
    # below and a free component along the rays, R1's cloth drifted in depth over its last frames (last-frame
    # CD2 2.41 against 0.84). With pins the penalty only hindered: pinned benchmark scenes 1.5-6x worse
    # (BENCHMARKS.md, "Affine acceleration field").
    force_along_weight: float = 1.0
    force_along_weight_pinned: float = 0.0
    # Point tracks (saft.reconstruct.tracks; not in the paper): λ of the track loss (0 = off, the paper),
    # the forward-backward check in pixels, and the Huber threshold in pixels beyond which a residual
    # counts linearly. With the backtracking and the final decay below, R1's mean CD2 falls from 2.6-3.0
    # to 0.91 (BENCHMARKS.md); without them the full 50 frames diverged.
    lambda_track: float = 2e3
    track_fb_threshold: float = 1.0
    track_huber: float = 3.0
    # Re-anchoring (pixels; 0 = chained flow only): where a frame's direct flow from frame 0 passes the
    # forward-backward check within this distance of the chained track, the track takes it (no drift).
    track_reanchor_radius: float = 2.0
    # A track also ends at its first step whose colour changes by more than this many times the video's
    # median step (never less than track_jump_floor, in [0, 1] RGB): a covered point whose track slid onto
    # a flap folding over it (saft.reconstruct.tracks; 0 = off). 8: on the fold scene it ends 324 of the
    # 363 track-frames that were > 4 px off and 0.7 % of those within 2 px (c_unpinned CD2 7.06 -> 3.91,
    # R1 0.451 -> 0.438, medians of 3); 6 also ended the grabbed corner's good tracks as it turned
    # (c_unpinned 13), 10 let more wrong ones through (4.16). BENCHMARKS.md, "Tracks end at colour jumps".
    track_jump_ratio: float = 8.0
    track_jump_floor: float = 0.03
    # A track also ends where the chromaticity under it drifts from its frame-0 one by more than this (0 =
    # off; saft.reconstruct.tracks.end_at_colour_drift): a track that slid slowly onto other threads.
    # Off by default: 0.02 took the independent side-gust scene from 23.3 to 15.1 and the wind scene from
    # 1.18 to 1.05, but R1 from 0.432 to 0.551 (it ends 29 % of R1's track-frames) and the flag from 19.0
    # to 21.1; 0.03 gave the flag 16.9, the side gust 19.1, the wind scene 1.05, one corner 24.4, but R1
    # 0.460 with its last frame 1.77x the mean against 1.50x (one run each; BENCHMARKS.md, "Why saft
    # loses the independent scenes"); at 627f785, R1 perturbation 1 with 0.03: 0.479 (last 1.09),
    # the default 0.425 (0.65). Kept off until repeats on both decide.
    track_drift: float = 0.0
    # Soft confidence instead of that cut (0 = off): each track-frame weighs exp(−(d / track_drift_scale)²)
    # in the track loss, d the chromaticity drift under it so far (saft.reconstruct.tracks.drift_confidence).
    # Off by default: 0.03 made all six independent-simulator scenes better or level (flag 19.1 -> 14.3,
    # side gust 23.1 -> 20.4, gust 1.20 -> 1.06, fold 1.16 -> 0.92, corners 1.33 -> 1.21, one corner 24.3;
    # median 10.2 -> 7.8; one run each, the flag and one corner repeated under perturbation), but R1 lost at
    # perturbations 1 and 3: 0.425 -> 0.461, 0.435 -> 0.459 (BENCHMARKS.md, "Soft track confidence, …").
    track_drift_scale: float = 0.0
    # Where the clip starts curved in motion (the silhouette's first change >= 0.3 of its median change and
    # the template clearly billowed: saft.scene.motion.starts_curved_in_motion), the whole
    # track loss weighs min(1, Q / track_texture), Q the median Shi–Tomasi texture strength of the tracks'
    # starts in frame 0 in units of the video's noise (saft.reconstruct.tracks.texture_confidence; 0 = off):
    # on a plain fabric the flow follows the shading. Q: cotton 0.02, lamé 0.02-0.04, plaid 0.01, satin
    # 0.12-0.15, print 0.79-1.09, Newton scenes 1.10-1.84, R1 27, the demo 112. 1: the appearance clips cut
    # at frame 24 satin 38.70 -> 3.50, cotton 86.44 -> 27.81, plaid 10.28 -> 0.95, lamé 27.12 -> 4.76, print
    # 0.300 -> 0.298 (0.5: satin 40.8, the satin needs the small weight); every other scene measured
    # identical (weight 1). Without the gate the same clips from rest: plaid +53 %, cotton +20 % (median of
    # 3), satin and lamé x0.36 / x0.24 (BENCHMARKS.md, "Track confidence on clips that start moving").
    # Not on a flat cloth already in a breeze (Newton's appearance clips): there the tracks weighed down
    # cost plaid 5.18 -> 16.11, satin 20.97 -> 35.5, lamé 16.02 -> 44.6, cotton 47.40 -> 57.6 (BENCHMARKS.md,
    # "Fourteenth session").
    track_texture: float = 1.0
    # Skip a track where the current reconstruction hides its vertex behind another part of the cloth by
    # more than the mean edge length (a fold the flow's forward-backward check let through).
    track_occlusion: bool = True
    # After antialias, multiply the rendered RGB and coverage by the hard coverage (the reference): only
    # the silhouette gradients that land on covered pixels survive.
    hard_coverage: bool = False
    optimize_stiffness: bool = True
    lr_stiffness: float = 2e-2
    lr_air_drag: float = 2e-2             # of log10 c, the air drag coefficient (physics.air_drag > 0; 0 = held)
    lr_const_accel: float = 1e-1
    lr_vertex_accel: float = 2e-1
    # Learning rate of a per-frame affine acceleration field over the template, added to the per-vertex
    # accelerations (saft.reconstruct.force_field; 0 = off, the paper): whole-cloth motions (a swing, a
    # sway in the wind) at the scale of gravity within a few epochs. 0.3: 1.0 overshot early and the step
    # guard cut every rate for the rest of the run (BENCHMARKS.md, "Affine acceleration field").
    lr_field_accel: float = 0.3
    # Learning rate of the first-order light vector of the relative shading (saft.render.shading; 0 = off,
    # the paper's unlit renderer): the shape renderer darkens or brightens each vertex as its normal turns
    # from frame 0's, so that a cloth tilting away from the light can be told from one tilting towards it.
    # On every cloth (plain_shading = 0) 0.05 halved the wind scene's error without pins (a_unpinned, median of
    # 3: 1.11 -> 0.62) but R1's median went 0.438 -> 0.461 (BENCHMARKS.md, "Relative shading in the shape
    # renderer"): by default the light is kept only on a plain fabric (plain_shading below). Unlit everywhere,
    # the paper: lr_light = 0 and plain_shading = 0.
    lr_light: float = 0.05
    # Where the light vector starts (saft.reconstruct.light); with lr_light = 0 and a non-zero vector, the
    # light is held there (a known light). World frame, in the shape renderer's convention: the sRGB colour
    # scales as 1 + light . n. (0, 0, 0) with lr_light = 0: unlit, the paper.
    light_init: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Q0 of the plain-fabric switch (saft.reconstruct.light.plain_cloth; 0 = off): where the tracks' median texture
    # strength Q at frame 0 is below Q0, the whole track loss weighs min(1, Q / track_texture) also from rest
    # and the light (lr_light > 0 or light_init) is kept; where Q >= Q0 the light is dropped (the unlit
    # run). Needs a light. 0.5 with lr_light 0.05 and light_init (0, 0.4, 0) (the appearance scenes' up), one
    # run each: cotton 8.25 -> 5.18, lamé 12.4 -> 1.51, satin 2.77 -> 1.05, plaid 0.875 -> 0.782, print and
    # every Newton scene / R1 (Q >= 1.1) unlit, identical (BENCHMARKS.md, "Shading as the shape cue of plain
    # cloth"). The default, with light_from_above 0.4, since 2026-11-27 (cotton 8.25 -> 5.85, lamé 12.4 -> 1.47,
    # satin 2.77 -> 1.05, plaid 0.875 -> 0.76 at b3013bf). A plain fabric in a clip that starts curved in
    # motion stays unlit: the light lost there (clips cut at frame 24: satin 3.49 -> 7.83, lamé 4.76 -> 9.55,
    # plaid 0.95 -> 1.14; cotton 27.8 -> 20.5). One already moving from a flat frame 0 keeps the light and its
    # tracks at full weight (Newton's appearance clips, against unlit with the tracks weighed down: plaid
    # 16.11 -> 5.18, satin 35.5 -> 20.97, lamé 44.6 -> 16.02, cotton 57.6 -> 47.40; with the tracks weighed
    # down: 12.35, 18.54, 31.07, 56.54; BENCHMARKS.md, "Fourteenth session").
    plain_shading: float = 0.5
    # The light also starts at this times the scene's up (−gravity, where the scene states gravity): a sky and a
    # sun above the cloth. 0.4 with plain_shading 0.5 and lr_light 0.05 gives the row of light_init (0, 0.4, 0) on
    # the appearance scenes (whose up is +y): cotton 5.18, lamé 1.51, satin 1.05, plaid 0.78.
    light_from_above: float = 0.4
    # Soft anchors (saft.physics.rollout's anchor; not in the paper): every vertex may be held at its
    # template position by a zero-length spring of learned stiffness per unit mass w, implicit like the
    # cloth's own forces, so that a cloth held at points nobody named hangs from them under gravity instead
    # of floating (a cloth held at two corners and swinging, nothing pinned: CD2 52.4 -> 0.62-0.64, 3 runs).
    # "auto" = on when the scene pins nothing and states its gravity (the anchored cloth hangs under
    # gravity; where the direction is only guessed, as for R1, the paper's floating cloth is kept: forced
    # on, R1 went 0.438 -> 0.60-0.85 with its last frame 2-3x the mean), "on", "off" (the paper).
    # log10 w starts at anchor_log10_init (every vertex held) and is learned by its own Adam (lr_anchor)
    # within anchor_log10_range; lambda_anchor weighs the held share (linear in log10 w up to w h² = 10,
    # flat above) so that the vertices the video does not need held are let go. With anchors on, the
    # constant acceleration starts at gravity. BENCHMARKS.md, "Soft anchors".
    anchors: Literal["auto", "on", "off"] = "auto"
    lr_anchor: float = 0.7
    anchor_log10_init: float = 9.0
    anchor_log10_range: tuple[float, float] = (0.0, 9.0)
    lambda_anchor: float = 1e-3
    # The velocity at frame 0 (saft.reconstruct.initial_velocity; not in the paper, which starts at rest): the
    # learning rate of its affine field (0 = off: at rest), learned only where the clip starts moving (the
    # tracks' first step beyond the physics from rest >= 0.3 of the clip's median step and >= 2.5x its
    # non-affine rest; else dropped, as at 0) and started from that step, and λ_V of its prior R_V (the mean
    # |v0|, m/s). 0.02, against 0: clips that start mid-motion (independent scenes from frame 8) corners 1.63
    # -> 1.39, gust 20.4 -> 5.76, fold 3.01 -> 2.20; at rest gust 1.16 -> 1.11, fold 1.10 -> 1.14 (its run-to-run
    # noise), corners, the demo, R1 and the saft-simulated twins: dropped, unchanged. Ungated it made the demo
    # 0.347 -> 0.483 (BENCHMARKS.md, "Learn v0 only where the clip starts moving"). Never with soft anchors
    # (they hold the template at rest): Newton's unpinned gust 17.5 with v0 learned, 1.28 without.
    lr_v0: float = 0.02
    lambda_v0: float = 1e-3
    normalize_loss: bool = True           # divide the loss by its detached value before backward
    grad_clip: float = 1e3
    autoclip_quantile: float = 0.75
    autoclip_history: int = 1000          # gradient norms kept for AutoClip (the reference: 11)
    autoclip_include_current: bool = True  # the current norm counts in its own quantile (reference: no)
    # Learning rates fall with a cosine over the final all-frame epochs to this fraction (1 = constant,
    # the reference); a constant rate leaves the loss oscillating at the end.
    final_lr_fraction: float = 0.1
    # Backtracking (saft.reconstruct.step_guard; not in the paper): an epoch whose loss exceeds
    # backtrack_ratio × the lowest loss with the same frames in use is rolled back to that lowest point and
    # every learning rate is multiplied by backtrack_decay from then on (0 = off, the paper).
    backtrack_ratio: float = 1.3
    backtrack_decay: float = 0.5
    # After this many epochs in a row without a backtrack, the rate is divided by backtrack_decay again, up
    # to the full rate (0 = a cut lasts for the rest of the run).
    backtrack_recover_epochs: int = 0
    # A cut applies only to the per-frame accelerations of the frames in use when it was made; a frame added
    # later is stepped without it (saft.reconstruct.new_frame_rate; False = every cut slows every later frame,
    # as before). On Newton's appearance clips an early cut (frame 9-13) left the late gust's frames at half
    # the rate and they fell behind the billow: print 11.02 -> 0.83, demo 0.358 -> 0.303, R1 perturbations
    # 0 / 1 / 3 0.416 / 0.438 / 0.500 -> 0.452 / 0.416 / 0.500, every run without an early cut bit for bit
    # (BENCHMARKS.md, "Newton's appearance clips: why the gust is lost…"; default since the fifteenth session).
    backtrack_new_frames: bool = True
    center_vertex_accel: bool = True      # subtract the mean per-vertex acceleration before each epoch
    warm_start_new_frames: bool = True    # a newly added frame starts from the previous frame's accelerations
    # Start of the constant acceleration: "gravity" (the reference), "zero", or "auto" = gravity when the
    # scene pins vertices or the soft anchors are on (they carry the weight), else zero: the template is
    # the rest shape, so a cloth at rest in frame 0 with nothing held is in equilibrium only with zero net
    # external force (without anchors, b_unpinned with gravity from the start: 19.1 against 0.64).
    const_accel_init: Literal["auto", "gravity", "zero"] = "auto"


@dataclass
class SaftConfig:
    run: RunConfig = field(default_factory=RunConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    # Phase 3 (saft.appearance). profile "auto": the paper's settings on CUDA, the measured CPU profile
    # (fewer epochs, frame mini-batches, lower resolution) on CPU; explicit values override either.
    appearance: AppearanceConfig = field(default_factory=lambda: AppearanceConfig(profile="auto"))


def shape_schedule(num_frames: int, cfg: ShapeConfig) -> list[int]:
    """Frames in use at each epoch of phase 2: initial_frames, +1 every add_frame_every epochs, then final_epochs."""
    first = min(num_frames, max(2, cfg.initial_frames))
    initial = cfg.initial_epochs if cfg.initial_epochs > 0 else cfg.add_frame_every
    frames = [first] * initial if first < num_frames else []
    for f in range(first + 1, num_frames):
        frames += [f] * cfg.add_frame_every
    return frames + [num_frames] * cfg.final_epochs


def load_saft_config(path: str | Path | None = None, overrides: list[str] | None = None) -> SaftConfig:
    """Defaults ← TOML file ← `--set` overrides, checked strictly; the appearance profile resolved.

    With appearance.profile = "auto", the appearance section starts from the CPU profile when the run
    will be on the CPU (else from the paper's settings) and the user's explicit appearance values are
    applied on top; the saved config.toml then names the profile it used ("cpu" or "cuda").
    """
    data = load_toml(path) if path else {}
    where = str(path) if path else "config"
    if overrides:
        data = merge_overrides(data, overrides)
        where = f"{path} + --set" if path else "--set"
    cfg = from_dict(SaftConfig, data, where)
    if cfg.appearance.profile == "auto":
        on_cpu = appearance_device(cfg.run.device).type == "cpu"
        base = cpu_profile(AppearanceConfig()) if on_cpu else cuda_profile(AppearanceConfig())
        user = {k: v for k, v in data.get("appearance", {}).items() if k != "profile"}
        cfg.appearance = from_dict(AppearanceConfig, {**to_dict(base), **user}, where, "appearance.")
    cfg.appearance.validate()
    check_config_ranges(cfg, where)
    return cfg
