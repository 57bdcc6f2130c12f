"""Phase 2, physics-based shape from template (paper section 3.3.2).

Each epoch simulates from the template through the frames in use and renders them with the fixed texture:

    L = λ_im·L_im + λ_sil·L_sil + λ_E·R_E + λ_F·R_F + λ_track·L_track + λ_A·R_A

L_im, L_sil: mean squared RGB / mask errors averaged over the frames in use; R_E: the deformation energy of the
simulated frames with the stiffnesses detached; R_F: the size of the external accelerations beyond the constant one,
their component along the viewing directions of the CURRENT simulated vertices (or the template's) weighted by
shape.force_along_weight (or force_along_weight_pinned when vertices are pinned; the paper: 0); L_track: the distance
of the projected vertices to their optical-flow point tracks (saft.reconstruct.tracks; not in the paper); R_A: the
held share of the soft anchors (ShapeSimulator.held_share; not in the paper); R_V: the size of the learned velocity
at frame 0 (saft.reconstruct.initial_velocity; not in the paper). The optimized parameters are log10 Y, B, S (clamped
to their ranges), a constant acceleration (gravity + mean wind), per-vertex per-frame accelerations and a per-frame
affine acceleration field over the template (saft.reconstruct.force_field; not in the paper) and the relative
shading's light (saft.reconstruct.light) and, with soft anchors (shape.anchors), log10 of each vertex's anchor
stiffness and, with shape.lr_v0 > 0, the affine velocity at frame 0 (from the tracks), each by its own clipped Adam.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.profiler import record_function

from saft.physics import ClothTopology, PhysicsParams, deformation_energy, rollout
from saft.physics.factor_cache import FactorCache
from saft.reconstruct.config import PhysicsConfig, ShapeConfig
from saft.reconstruct.frame_schedule import FrameSchedule, lr_factor, window_first_frame
from saft.reconstruct.context import PhaseContext
from saft.reconstruct.force_field import affine_basis
from saft.reconstruct.initial_velocity import start_velocity, velocity_prior
from saft.reconstruct.light import curved_start_in_motion, initial_light, plain_cloth
from saft.reconstruct.frame_renders import FrameRenders
from saft.reconstruct.losses import force_regularizer
from saft.reconstruct import new_frame_rate
from saft.reconstruct.silhouette_reach import reach_px
from saft.reconstruct.optim import ClippedAdam, ParamSpec
from saft.reconstruct.shape_params import STIFFNESSES, FrameStates, ShapeParams
from saft.reconstruct.step_guard import StepGuard
from saft.reconstruct.air_drag import run_damping_and_drag
from saft.reconstruct.swing_weights import swing_shape_config
from saft.reconstruct.tracks import VertexTracks, compute_vertex_tracks, hidden_vertices, track_loss
from saft.reconstruct.window_hold import outside_window, per_frame, restore_outside_window

@dataclass
class ShapeState:
    params: ShapeParams
    optimizer: ClippedAdam
    guard: StepGuard
    epoch: int = 0
    states: FrameStates | None = None
    schedule: dict | None = None   # FrameSchedule.state_dict() after the last epoch
    damping: float | None = None   # the run's velocity damping, chosen before the first epoch (swing_damping)
    # the solver's factors from earlier epochs' rollouts (physics/factor_cache.py), checkpointed with the rest
    factors: FactorCache = field(default_factory=FactorCache)

    def state_dict(self) -> dict:
        saved = {"params": {k: v.detach().cpu() for k, v in self.params.tensors().items()},
                 "optimizer": self.optimizer.state_dict(), "epoch": self.epoch, "guard": self.guard.state_dict(),
                 "schedule": self.schedule, "factors": self.factors.state_dict(), "damping": self.damping}
        if self.states is not None:
            saved["frame_states"] = {"x": self.states.x.cpu(), "v": self.states.v.cpu(), "frames": self.states.frames,
                                     "fresh": self.states.fresh}
        return saved


def _make_optimizer(params: ShapeParams, cfg: ShapeConfig) -> ClippedAdam:
    specs = [ParamSpec("const_accel", params.const_accel, cfg.lr_const_accel),
             ParamSpec("vertex_accel", params.vertex_accel, cfg.lr_vertex_accel)]
    if params.field_accel is not None:
        specs.append(ParamSpec("field_accel", params.field_accel, cfg.lr_field_accel))
    if params.light is not None and cfg.lr_light > 0:   # a held light (lr 0) is never stepped
        specs.append(ParamSpec("light", params.light, cfg.lr_light))
    if params.anchor_log10 is not None:
        specs.append(ParamSpec("anchor_log10", params.anchor_log10, cfg.lr_anchor))
    if params.v0_field is not None:
        specs.append(ParamSpec("v0_field", params.v0_field, cfg.lr_v0))
    if params.log10_drag is not None and cfg.lr_air_drag > 0:   # a held drag (lr 0) is never stepped
        specs.append(ParamSpec("log10_drag", params.log10_drag, cfg.lr_air_drag))
    if cfg.optimize_stiffness:
        specs += [ParamSpec(n, getattr(params, n), cfg.lr_stiffness) for n in STIFFNESSES]
    return ClippedAdam(specs, clip=cfg.grad_clip, quantile=cfg.autoclip_quantile, history=cfg.autoclip_history,
                       include_current=cfg.autoclip_include_current)


def _make_guard(cfg: ShapeConfig) -> StepGuard:
    return StepGuard(ratio=cfg.backtrack_ratio, decay=cfg.backtrack_decay, recover_after=cfg.backtrack_recover_epochs)


def anchors_on(pinned, cfg: ShapeConfig, gravity_stated: bool = True) -> bool:
    """Whether the run learns soft anchors: shape.anchors; "auto" = when the scene pins nothing and states
    its gravity (the anchored cloth hangs under gravity: a guessed direction is no base for it)."""
    if cfg.anchors == "auto":
        return (pinned is None or len(pinned) == 0) and gravity_stated
    return cfg.anchors == "on"


def initial_const_accel(gravity: np.ndarray, pinned, cfg: ShapeConfig, gravity_stated: bool = True) -> np.ndarray:
    mode = cfg.const_accel_init
    if mode == "auto":
        held = (pinned is not None and len(pinned) > 0) or anchors_on(pinned, cfg, gravity_stated)
        mode = "gravity" if held else "zero"
    return np.asarray(gravity, dtype=np.float64) if mode == "gravity" else np.zeros(3)


def new_shape_state(num_frames: int, num_vertices: int, gravity: np.ndarray, phys: PhysicsConfig,
                    cfg: ShapeConfig, device, dtype=torch.float64, anchors: bool = False, up=None) -> ShapeState:
    """Fresh parameters; `gravity` is the initial constant acceleration (see initial_const_accel); `up`: the
    scene's unit up (light.scene_up) for shape.light_from_above."""
    def scalar(v):
        return torch.tensor(float(v), dtype=dtype, device=device, requires_grad=cfg.optimize_stiffness)

    params = ShapeParams(
        log10_Y=scalar(phys.log10_Y_init), log10_B=scalar(phys.log10_B_init), log10_S=scalar(phys.log10_S_init),
        const_accel=torch.tensor(np.asarray(gravity, dtype=np.float64), dtype=dtype, device=device).requires_grad_(True),
        vertex_accel=torch.zeros(max(num_frames - 1, 0), num_vertices, 3, dtype=dtype, device=device,
                                 requires_grad=True),
        field_accel=(torch.zeros(max(num_frames - 1, 0), 4, 3, dtype=dtype, device=device, requires_grad=True)
                     if cfg.lr_field_accel > 0 else None),
        light=initial_light(cfg, dtype, device, up),
        anchor_log10=(torch.full((num_vertices,), float(cfg.anchor_log10_init), dtype=dtype, device=device,
                                 requires_grad=True) if anchors else None),
        v0_field=torch.zeros(4, 3, dtype=dtype, device=device, requires_grad=True) if cfg.lr_v0 > 0 else None,
        log10_drag=(torch.tensor(math.log10(phys.air_drag), dtype=dtype, device=device, requires_grad=True)
                    if phys.air_drag > 0 else None))
    return ShapeState(params, _make_optimizer(params, cfg), _make_guard(cfg))


def restore_shape_state(saved: dict, cfg: ShapeConfig, device) -> ShapeState:
    p = {k: v.to(device).requires_grad_(k not in STIFFNESSES or cfg.optimize_stiffness)
         for k, v in saved["params"].items()}
    params = ShapeParams(**p)
    state = ShapeState(params, _make_optimizer(params, cfg), _make_guard(cfg), saved["epoch"],
                       schedule=saved.get("schedule"), damping=saved.get("damping"))
    state.optimizer.load_state_dict(saved["optimizer"])
    state.guard.load_state_dict(saved.get("guard", {}))
    state.factors.load_state_dict(saved.get("factors", {}))
    if "frame_states" in saved:
        fs = saved["frame_states"]
        state.states = FrameStates(fs["x"].to(device), fs["v"].to(device), int(fs["frames"]), int(fs.get("fresh", 1)))
    return state


class ShapeSimulator:
    """The cloth simulation of the scene, as a function of the shape parameters."""

    def __init__(self, template: torch.Tensor, quads: np.ndarray, phys: PhysicsConfig, frame_dt: float,
                 pinned: np.ndarray | None):
        self.phys, self.frame_dt, self.damping = phys, frame_dt, phys.damping   # damping: see run_shape_phase
        self.template = template
        self.quads = quads
        self.rest_shape = None
        self.use_rest_shape("flat" if phys.rest_shape == "flat" else "template")
        self.pinned = None if pinned is None or len(pinned) == 0 else torch.as_tensor(pinned, device=template.device)
        self.mean_edge_length = float(self.topology.rest_len.mean())
        self.field_basis = affine_basis(template.detach())

    def use_rest_shape(self, rest_shape: str) -> None:
        """(Re)build the topology with rest angles "template" or "flat" (physics.rest_shape); kept if unchanged."""
        if rest_shape == self.rest_shape:
            return
        self.rest_shape = rest_shape
        t = self.template
        self.topology = ClothTopology.from_quads(t.detach().cpu().numpy(), self.quads, density=self.phys.density,
                                                 device=t.device, dtype=t.dtype, rest_shape=rest_shape)

    def simulate(self, params: ShapeParams, num_frames: int, factors: FactorCache | None = None,
                 on_frame=None) -> torch.Tensor:
        """(num_frames, V, 3) positions, frame 0 = template; `factors`: the solver's cache across epochs;
        `on_frame`: rollout's, called with (frame, positions) as each is done."""
        accel = params.accelerations(self.field_basis, 0, num_frames - 1)
        v0 = params.velocity(self.field_basis)
        return rollout(self.topology, self.template, v0, self._physics(params, accel), num_frames=num_frames,
                       substeps=self.phys.substeps, frame_dt=self.frame_dt, pinned=self.pinned,
                       hessian=self.phys.hessian, anchor_positions=self.template, factor_cache=factors,
                       on_frame=on_frame)

    def simulate_from(self, params: ShapeParams, start: int, num_frames: int, x0: torch.Tensor | None = None,
                      v0: torch.Tensor | None = None, factors: FactorCache | None = None,
                      on_frame=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames start..num_frames-1 from the state (x0, v0) at frame `start` (None: the template, with the
        learned velocity at frame 0 or at rest):
        positions and velocities at each frame boundary, (num_frames - start, V, 3) each. `on_frame`: called
        with (frame - start, positions) as each frame is done.

        The rollout is asked for every substep as a frame of its own (the same steps as simulate()), so
        that the velocity at a frame boundary is exact: v = (x_k − x_k⁻) / h.
        """
        S = self.phys.substeps
        n = num_frames - start
        x0 = self.template if x0 is None else x0
        if v0 is None:   # from frame 0: the learned velocity (None when not learned); later: at rest
            v0 = params.velocity(self.field_basis) if start == 0 else None
            v0 = torch.zeros_like(x0) if v0 is None else v0
        a_sub = params.accelerations(self.field_basis, start, num_frames - 1).repeat_interleave(S, dim=0)
        pos = rollout(self.topology, x0, v0, self._physics(params, a_sub), num_frames=(n - 1) * S + 1, substeps=1,
                      frame_dt=self.frame_dt / S, pinned=self.pinned, hessian=self.phys.hessian,
                      anchor_positions=self.template, factor_cache=factors, first_step=start * S,
                      on_frame=None if on_frame is None else lambda j, x: on_frame(j // S, x) if j % S == 0 else None)
        x = pos[::S]
        v = torch.cat([v0[None], (pos[S::S] - pos[S - 1::S]) / (self.frame_dt / S)], dim=0)
        return x, v

    def _physics(self, params: ShapeParams, a_vert: torch.Tensor):
        damping = torch.tensor(self.damping, dtype=self.template.dtype, device=self.template.device)
        anchor = None if params.anchor_log10 is None else 10.0 ** params.anchor_log10
        return PhysicsParams(log10_Y=params.log10_Y, log10_B=params.log10_B, log10_S=params.log10_S,
                             damping=damping, a_const=params.const_accel, a_vert=a_vert, anchor=anchor,
                             log10_drag=params.log10_drag)

    def held_share(self, params: ShapeParams, floor: float) -> torch.Tensor:
        """R_A: the mean over vertices of how far each soft anchor holds its vertex, linear in log10 w from
        `floor` (0) to w h² = 10 (1, held) and flat above: a held vertex is then free to be held harder
        (a saturating share such as w h² / (1 + w h²) still has a small gradient there, which Adam scales
        up to full steps and which softened every anchor until the data noticed). 0 when anchors are off."""
        if params.anchor_log10 is None:
            return params.const_accel.new_zeros(())
        h = self.frame_dt / self.phys.substeps
        held_at = math.log10(10.0 / (h * h))
        return ((params.anchor_log10 - floor) / max(held_at - floor, 1e-6)).clamp(0.0, 1.0).mean()

    def energy(self, positions: torch.Tensor, params: ShapeParams) -> torch.Tensor:
        """Deformation energy of each frame (F,), stiffnesses detached (for R_E)."""
        return deformation_energy(positions, self.topology, params.log10_Y.detach(), params.log10_B.detach(),
                                  params.log10_S.detach())


def simulate_epoch(sim: ShapeSimulator, state: ShapeState, frames: int, start: int, on_frame=None) -> torch.Tensor:
    """Positions of frames start..frames-1 with graph; windowed runs also refresh the stored states.
    `on_frame`: called with (frame - start, positions) as each frame of the graph's rollout is done."""
    if state.states is None:
        return sim.simulate(state.params, frames, state.factors, on_frame)
    st = state.states
    if 0 < start and st.fresh <= start:
        # Bring the stored states up to the window's start under the current parameters (forward only).
        s0 = st.fresh - 1
        with torch.no_grad():
            x0, v0 = (st.x[s0].clone(), st.v[s0].clone()) if s0 > 0 else (None, None)
            st.update(s0, *sim.simulate_from(state.params, s0, start + 1, x0, v0, state.factors))
    # clones: the rollout keeps its start state for the backward, and update() writes into the store
    x0, v0 = (st.x[start].clone(), st.v[start].clone()) if start > 0 else (None, None)
    x, v = sim.simulate_from(state.params, start, frames, x0, v0, state.factors, on_frame)
    st.update(start, x, v)
    return x


def window_start(frames: int, epoch: int, final: bool, states: FrameStates | None, cfg: ShapeConfig) -> int:
    """First frame simulated in this epoch: frame_schedule.window_first_frame, or 0 while the stored states
    do not reach it yet."""
    if states is None:
        return 0
    start = window_first_frame(frames, epoch, final, cfg)
    return start if start < states.frames else 0


def along_ray_weight(cfg: ShapeConfig, sim: ShapeSimulator) -> float:
    """R_F's weight on the acceleration's component along the viewing ray: pins hold the depth, or nothing does."""
    return cfg.force_along_weight if sim.pinned is None else cfg.force_along_weight_pinned


def _regularizers(ctx: PhaseContext, sim: ShapeSimulator, params: ShapeParams, cfg: ShapeConfig,
                  positions: torch.Tensor, depths: list, tracks: VertexTracks | None, start: int, frames: int):
    """The physics side's terms (float64): (energy, force, track, held, R_V, their weighted sum)."""
    n_win = frames - start
    energy = sim.energy(positions, params).mean()
    cam_center = torch.as_tensor(ctx.camera.center, dtype=positions.dtype, device=positions.device)
    if n_win > 1:
        accel = params.accelerations(sim.field_basis, start, frames - 1)
        if cfg.force_target == "total":
            accel = accel + params.const_accel
        dir_pos = positions[1:] if cfg.force_directions == "current" else sim.template.expand(n_win - 1, -1, -1)
        force = force_regularizer(accel, dir_pos, cam_center, along_ray_weight(cfg, sim))
    else:
        force = torch.zeros((), dtype=positions.dtype, device=positions.device)
    if tracks is not None:
        hidden = (hidden_vertices(positions, depths, ctx.camera, sim.mean_edge_length) if depths
                  else None)
        track = track_loss(positions, tracks, ctx.camera, cfg.track_huber, first_frame=start, hidden=hidden)
    else:
        track = torch.zeros((), dtype=positions.dtype, device=positions.device)
    held = sim.held_share(params, cfg.anchor_log10_range[0])
    v0 = velocity_prior(params.velocity(sim.field_basis) if start == 0 else None, energy)
    reg = (cfg.lambda_energy * energy + cfg.lambda_force * force + cfg.lambda_track * track
           + cfg.lambda_anchor * held + cfg.lambda_v0 * v0)
    return energy, force, track, held, v0, reg


def epoch_loss_and_grad(ctx: PhaseContext, sim: ShapeSimulator, state: ShapeState, cfg: ShapeConfig,
                        texture: torch.Tensor, frames: int, tracks: VertexTracks | None = None,
                        start: int = 0) -> dict[str, float]:
    """Forward + backward of one epoch over frames start..frames-1 (start > 0: a window from a stored,
    detached state); leaves the gradients in the parameters. Returns the loss terms."""
    params = state.params
    # record_function ranges (no cost without a profiler): benchmarks/bench_r1.py --profile splits a run by them
    # Every frame rendered and differentiated (in chunks; on the CPU with cores to spare, on a pool of threads,
    # each frame as soon as the physics has it). The renders may run on another device than the physics.
    light = params.light.to(device=ctx.device, dtype=torch.float32) if params.light is not None else None
    renders = FrameRenders(ctx, cfg, light, texture, start, frames - start, reach_px(cfg, sim.pinned),
                           tracks is not None and cfg.track_occlusion, ctx.render_threads)
    with record_function("saft.shape.simulate"):
        positions = simulate_epoch(sim, state, frames, start, renders.frame_ready if renders.streaming else None)
    pos_leaf = positions.detach().to(device=ctx.device, dtype=torch.float32).requires_grad_(True)
    with record_function("saft.shape.render"):
        sums, depths = renders.finish(pos_leaf)
    depths = [d.to(positions.device) for d in depths]

    # Regularizers on the physics side (float64).
    with record_function("saft.shape.regularizers"):
        energy, force, track, held, v0, reg = _regularizers(ctx, sim, params, cfg, positions, depths, tracks,
                                                            start, frames)
    grad_pos = pos_leaf.grad.to(positions) if pos_leaf.grad is not None else torch.zeros_like(positions)
    with record_function("saft.shape.backward"):   # the physics' adjoint and the regularizers' backward
        torch.autograd.backward([positions, reg], [grad_pos, torch.ones_like(reg)])

    total = (cfg.lambda_image * sums["image"] + cfg.lambda_sil * sums["silhouette"]
             + cfg.lambda_energy * float(energy.detach()) + cfg.lambda_force * float(force.detach())
             + cfg.lambda_track * float(track.detach()) + cfg.lambda_anchor * float(held.detach())
             + cfg.lambda_v0 * float(v0.detach()))
    if cfg.normalize_loss and total > 0:
        # Dividing the loss by its detached value scales every gradient by 1/L (scale-free steps).
        for t in params.tensors().values():
            if t.grad is not None:
                t.grad.div_(total)
    return {"loss": total, "energy": float(energy.detach()), "force": float(force.detach()),
            "track": float(track.detach()), "held": float(held.detach()), "v0": float(v0.detach()), **sums}


def shape_tracks(ctx: PhaseContext, cfg: ShapeConfig, texture: torch.Tensor, template: torch.Tensor) -> VertexTracks | None:
    """Point tracks of `template`'s vertices (on the physics device) through the targets, or None when the
    track loss is off."""
    if cfg.lambda_track <= 0 or ctx.target_rgb.shape[0] < 2:
        return None
    with torch.no_grad():
        depth0 = ctx.render(ctx.template_positions[None].to(torch.float32), texture).depth[0]
    texture_q0 = cfg.track_texture if cfg.track_texture > 0 and curved_start_in_motion(ctx) else 0.0
    return compute_vertex_tracks(ctx.target_rgb, ctx.target_mask, template, ctx.camera, depth0,
                                 cfg.track_fb_threshold, cfg.track_reanchor_radius, cfg.track_jump_ratio,
                                 cfg.track_jump_floor, cfg.track_drift, cfg.track_drift_scale, texture_q0)


def run_shape_phase(ctx: PhaseContext, sim: ShapeSimulator, state: ShapeState, phys: PhysicsConfig,
                    cfg: ShapeConfig, texture: torch.Tensor) -> torch.Tensor:
    """Optimize through the frame schedule (continuing from state.epoch); returns all frames' positions."""
    n_frames = ctx.target_rgb.shape[0]
    sched = FrameSchedule.restore(n_frames, cfg, state.schedule, state.epoch)
    ranges = {"log10_Y": phys.log10_Y_range, "log10_B": phys.log10_B_range, "log10_S": phys.log10_S_range,
              "anchor_log10": cfg.anchor_log10_range, "log10_drag": tuple(map(math.log10, phys.air_drag_range))}
    with record_function("saft.shape.tracks"):
        tracks = shape_tracks(ctx, cfg, texture, sim.template)
        tracks = plain_cloth(ctx, state, cfg, texture, sim.template, tracks)
    if state.epoch == 0 and state.params.v0_field is not None:   # seeded from the tracks, or dropped at rest
        start_velocity(state.params, state.optimizer, sim, tracks, ctx.camera)
        if phys.rest_shape == "moving" and state.params.v0_field is not None:   # the clip starts in motion:
            sim.use_rest_shape("flat")          # flat at rest, and v0 seeded again (from 0) beyond the
            with torch.no_grad():               # physics from that rest, as with "flat"
                state.params.v0_field.zero_()
            start_velocity(state.params, state.optimizer, sim, tracks, ctx.camera)
    if phys.rest_shape == "moving":             # flat exactly when v0 is learned (so a resumed run agrees)
        sim.use_rest_shape("flat" if state.params.v0_field is not None else "template")
    state.damping = sim.damping = run_damping_and_drag(state, sim, tracks, ctx.camera, phys)   # and air_drag_where
    cfg = swing_shape_config(cfg, phys, state.damping)
    if cfg.window > 0 and state.states is None:
        zeros = sim.template.new_zeros((n_frames,) + tuple(sim.template.shape))
        state.states = FrameStates(zeros.clone(), zeros.clone(), 1)
        state.states.x[0] = sim.template
    ctx.progress.start_phase("shape", sched.total_epochs, state.epoch)
    while not sched.done:
        t0 = time.perf_counter()
        frames = sched.frames
        params = state.params
        if cfg.warm_start_new_frames and sched.just_added and frames - 1 >= 2:
            # Wind changes smoothly: the new transition starts from the last optimized one, not from zero.
            with torch.no_grad():
                for t in per_frame(params):
                    t[frames - 2] = t[frames - 3]
        start = window_start(frames, state.epoch, sched.final, state.states, cfg)
        if cfg.center_vertex_accel and params.vertex_accel.numel() and start == 0:
            with torch.no_grad():
                params.vertex_accel -= params.vertex_accel.mean(dim=(0, 1), keepdim=True)
        state.optimizer.zero_grad()
        terms = epoch_loss_and_grad(ctx, sim, state, cfg, texture, frames, tracks, start)
        with record_function("saft.shape.step"):
            if start == 0:   # a window's loss covers other frames: not comparable
                state.guard.check(frames, terms["loss"], params.tensors(), state.optimizer)
            lr = lr_factor(state.epoch, sched.first_final_epoch(state.epoch), cfg) * state.guard.lr_scale
            state.optimizer.set_lr_factor(lr)
            frozen = outside_window(params, start)
            new_frame_rate.step(state.optimizer, params, state.guard, frames, cfg.backtrack_new_frames)
            restore_outside_window(params, start, frozen)
        if state.states is not None:   # a full pass's step moved every acceleration: refresh before the next window
            state.states.stepped(start)
        with torch.no_grad():
            for name, (lo, hi) in ranges.items():
                if getattr(params, name) is not None:
                    getattr(params, name).clamp_(lo, hi)
        state.epoch += 1
        sched.epoch_done(terms["loss"])
        state.schedule = sched.state_dict()
        ctx.log.add(phase="shape", epoch=state.epoch - 1, frames=frames, seconds=time.perf_counter() - t0,
                    lr_factor=lr, backtracks=state.guard.backtracks, **terms)
        ctx.progress.update(state.epoch - 1, frames, terms["loss"], total=sched.total_epochs)
        ctx.epoch_done("shape", state.epoch, state.state_dict)
    ctx.progress.end_phase()
    with torch.no_grad():
        return sim.simulate(state.params, n_frames)
