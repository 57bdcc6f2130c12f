"""The pipeline: Scene → texture phase → shape phase → outputs → (appearance phase) → result folder.

It only sequences the phases, checkpoints between them, and keeps the timings; the phases themselves live
in their own modules and do not reach into each other. Every phase follows one protocol: it takes the
PhaseContext (saft.reconstruct.context) and its inputs, and reports epochs through ctx.epoch_done or
ctx.checkpoint / ctx.check_interrupt; reconstruct() loops over the table PHASES.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from saft.appearance import profile_for_device
from saft.config_io import to_toml
from saft.device import cpu_threads, plan_devices
from saft.errors import SaftInputError
from saft.io_utils import atomic_write_json, atomic_write_text
from saft.reconstruct.appearance_outputs import run_appearance_phase, write_appearance_renders
from saft.reconstruct.checkpoint import (CheckpointClock, InterruptGuard, Interrupted, checkpoint_path,
                                         load_checkpoint)
from saft.reconstruct.config import SaftConfig
from saft.reconstruct.config_checks import check_config_ranges
from saft.reconstruct.context import PhaseContext, to_device_targets
from saft.reconstruct.estimate import log_estimate
from saft.reconstruct.frame_renders import render_threads
from saft.reconstruct.light import scene_up
from saft.reconstruct.out_dir import check_out_dir, create_out_dir
from saft.reconstruct.outputs import write_shape_outputs
from saft.reconstruct.progress import EpochLog, Progress
from saft.reconstruct.run_identity import check_same_run, run_identity
from saft.reconstruct.shape_phase import (ShapeSimulator, anchors_on, initial_const_accel, new_shape_state,
                                          restore_shape_state, run_shape_phase)
from saft.reconstruct.texture_phase import initial_texture, new_texture_state, restore_texture_state, run_texture_phase
from saft.render import get_rasterizer
from saft.scene import Scene
from saft.scene.scene import MIN_IMAGE_SIDE

log = logging.getLogger("saft")

CHECKPOINT_VERSION = 2   # 2: the run's identity (scene + config) is stored for --resume


@dataclass
class RunOutcome:
    out_dir: Path
    positions: np.ndarray                  # (N, V, 3) world frame
    texture: np.ndarray                    # (S, S, 3) sRGB
    params: dict
    timings: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------- phases
# Each runs one phase of the run in `state` (the checkpoint) and stores its results there.
def _texture_phase(ctx: PhaseContext, scene: Scene, cfg: SaftConfig) -> None:
    state = ctx.state
    if cfg.texture.enabled:
        ts = (restore_texture_state(cfg.texture, state["texture_state"], ctx.device) if "texture_state" in state
              else new_texture_state(cfg.texture, scene.texture, ctx.device))
        texture = run_texture_phase(ctx, cfg.texture, ts)
    else:
        texture = initial_texture(cfg.texture, scene.texture, ctx.device)
    state.pop("texture_state", None)
    state["texture"] = texture.cpu()


def _shape_phase(ctx: PhaseContext, scene: Scene, cfg: SaftConfig) -> None:
    state = ctx.state
    texture = state["texture"].to(ctx.device)
    physics = ctx.devices.physics
    sim = ShapeSimulator(ctx.template_positions.to(physics), scene.template.quads, cfg.physics, scene.frame_dt,
                         scene.pinned)
    stated = scene.gravity is not None
    ss = (restore_shape_state(state["shape_state"], cfg.shape, physics) if "shape_state" in state
          else new_shape_state(scene.num_frames, scene.template.num_vertices,
                               initial_const_accel(scene.gravity_or_default(), scene.pinned, cfg.shape, stated),
                               cfg.physics, cfg.shape, physics, anchors=anchors_on(scene.pinned, cfg.shape, stated),
                               up=scene_up(scene.gravity)))
    if cfg.shape.enabled:
        # frames rendered side by side: each render on one torch thread (the physics toggles torch's thread
        # count around its rollouts, which must not change under a running render)
        threads = torch.get_num_threads()
        if ctx.render_threads > 1:
            torch.set_num_threads(1)
        try:
            positions = run_shape_phase(ctx, sim, ss, cfg.physics, cfg.shape, texture)
        finally:
            torch.set_num_threads(threads)
    else:
        with torch.no_grad():
            positions = sim.simulate(ss.params, scene.num_frames)
    state["shape_state"] = ss.state_dict()
    state["positions"] = positions.detach().cpu()


def _outputs_phase(ctx: PhaseContext, scene: Scene, cfg: SaftConfig) -> None:
    state = ctx.state
    params = shape_params_summary(state["shape_state"], cfg, scene)
    write_shape_outputs(ctx.out_dir, scene, ctx.camera, state["positions"].numpy(), state["texture"].to(ctx.device),
                        state["shape_state"]["params"], params, ctx)


def _appearance_phase(ctx: PhaseContext, scene: Scene, cfg: SaftConfig) -> None:
    positions = ctx.state["positions"].numpy()
    result = run_appearance_phase(ctx, cfg.appearance, positions, scene.template.triangles, scene.template.uvs,
                                  ctx.state.get("appearance_state"), ctx.state["texture"].numpy())
    write_appearance_renders(ctx.out_dir, result, positions, scene.template.triangles, scene.template.uvs,
                             ctx.camera, ctx.target_rgb.cpu().numpy(), ctx.devices.appearance)
    ctx.state.pop("appearance_state", None)


@dataclass(frozen=True)
class Phase:
    name: str                                                   # the checkpoint's "phase" while it is to run
    run: Callable[[PhaseContext, Scene, SaftConfig], None]
    interruptible: bool = True     # Ctrl-C stops it at an epoch boundary (else Python's KeyboardInterrupt)
    writes_results: bool = False   # log.csv and timings.json are rewritten after it
    enabled: Callable[[SaftConfig], bool] = lambda cfg: True   # False: skipped (texture and shape always
    # run: with enabled = false in their config they produce the initial texture / the initial simulation)


PHASES = (
    Phase("texture", _texture_phase),
    Phase("shape", _shape_phase),
    Phase("outputs", _outputs_phase, interruptible=False, writes_results=True),
    Phase("appearance", _appearance_phase, writes_results=True, enabled=lambda cfg: cfg.appearance.enabled),
)


def _next_phase(name: str, cfg: SaftConfig) -> str:
    """The phase after `name` in PHASES that `cfg` enables, or "done"."""
    later = PHASES[[p.name for p in PHASES].index(name) + 1:]
    return next((p.name for p in later if p.enabled(cfg)), "done")


def reconstruct(scene: Scene, cfg: SaftConfig, out_dir: str | Path, *, resume: bool = False,
                overwrite: bool = False, quiet: bool = False,
                on_epoch: Callable[[str, int], None] | None = None) -> RunOutcome:
    """Run every enabled phase on `scene` and write the result folder `out_dir` (layout: saft.result).

    `on_epoch(phase, epochs_done)` is called after every epoch of every phase; returning True acts like
    Ctrl-C. Ctrl-C stops at the end of the current epoch after writing the checkpoint (KeyboardInterrupt
    is raised then), and `resume=True` continues from it (only with the same scene and result-determining
    config). `out_dir` must be new, empty, or a saft result with `resume` or `overwrite`
    (saft.reconstruct.out_dir); every input is checked before anything is written.
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    check_config_ranges(cfg)
    check_out_dir(out_dir, scene, resume=resume, overwrite=overwrite)
    devices = plan_devices(cfg.run.device, vertices=scene.template.num_vertices, appearance=cfg.appearance.enabled,
                           rasterizer=cfg.render.backend)
    device = devices.render
    for line in devices.lines():
        log.info("device: %s", line)
    if cfg.appearance.profile == "auto":   # programmatic use; the CLI resolves it in load_saft_config
        cfg = replace(cfg, appearance=profile_for_device(devices.appearance,
                                                         replace(cfg.appearance, profile="paper")))
    torch.set_num_threads(cpu_threads(cfg.run.threads))
    torch.manual_seed(cfg.run.seed)
    np.random.seed(cfg.run.seed)

    saved = load_checkpoint(out_dir, CHECKPOINT_VERSION) if resume else None
    if resume and saved is None:
        log.warning("no checkpoint in %s: starting from the beginning", out_dir)

    camera = scene.working_camera(cfg.render.scale)
    if min(camera.width, camera.height) < MIN_IMAGE_SIDE:
        raise SaftInputError("render.scale", f"= {cfg.render.scale:g} makes the working image {camera.width}x"
                                             f"{camera.height} pixels; saft needs at least {MIN_IMAGE_SIDE} per side")
    frames = scene.working_frames(cfg.render.scale)
    t_load = time.perf_counter()
    rgb, mask = frames.load()
    identity = run_identity(scene, cfg, rgb, mask)
    if saved is not None:
        check_same_run(saved["identity"], identity, checkpoint_path(out_dir))
    template = torch.as_tensor(scene.template.vertices, dtype=torch.float64, device=device)
    phase_now = saved["phase"] if saved else "texture"
    sim = None
    if phase_now in ("texture", "shape"):
        try:   # the template is checked by the physics before any phase runs (and the estimate uses it)
            sim = ShapeSimulator(template.to(devices.physics), scene.template.quads, cfg.physics, scene.frame_dt, scene.pinned)
        except ValueError as exc:
            raise SaftInputError(scene.source, f"the template cannot be simulated: {exc}") from None
    create_out_dir(out_dir, overwrite=overwrite)
    atomic_write_text(out_dir / "config.toml", to_toml(cfg))
    target_rgb, target_mask = to_device_targets(rgb, mask, device)
    timings: dict = dict(saved["timings"]) if saved else {}
    t_counted = time.perf_counter() - t_load  # the frames, then also the estimate
    timings["load_frames"] = timings.get("load_frames", 0.0) + t_counted
    ctx = PhaseContext(
        device=device, devices=devices, camera=camera,
        template_positions=template,
        triangles=torch.as_tensor(scene.template.triangles, dtype=torch.int32, device=device),
        uvs=torch.as_tensor(scene.template.uvs, dtype=torch.float32, device=device),
        target_rgb=target_rgb, target_mask=target_mask,
        rasterizer=get_rasterizer(cfg.render.backend, device), progress=Progress(quiet=quiet),
        render_threads=render_threads(cfg.run.render_threads, device),
        log=EpochLog(saved["log"] if saved else None), out_dir=out_dir,
        state=saved or {"version": CHECKPOINT_VERSION, "phase": "texture", "identity": identity}, timings=timings,
        guard=InterruptGuard(), clock=CheckpointClock(cfg.run.checkpoint_seconds), on_epoch=on_epoch,
    )
    if sim is not None:
        # the first physics step on CUDA compiles its kernels here (torch.compile, cached on disk afterwards)
        t_est = time.perf_counter()
        log_estimate(ctx, sim, cfg, scene.num_frames, scene.gravity_or_default())
        t_est = time.perf_counter() - t_est
        t_counted += t_est
        timings["estimate"] = timings.get("estimate", 0.0) + t_est
    # the rest of what comes before the phases: checks, the device plan (nvdiffrast's probe), the rasterizer
    timings["setup"] = timings.get("setup", 0.0) + time.perf_counter() - t_start - t_counted
    state = ctx.state
    for phase in PHASES:
        if state["phase"] != phase.name:
            continue
        t0 = time.perf_counter()
        try:
            if phase.interruptible:
                with ctx.guard.active():
                    phase.run(ctx, scene, cfg)
            else:
                phase.run(ctx, scene, cfg)
        except Interrupted as exc:
            ctx.progress.end_phase()
            ctx.log.write(out_dir / "log.csv")
            raise KeyboardInterrupt(str(exc)) from None
        timings[phase.name] = timings.get(phase.name, 0.0) + time.perf_counter() - t0
        state["phase"] = _next_phase(phase.name, cfg)
        if phase.writes_results:
            ctx.log.write(out_dir / "log.csv")
            atomic_write_json(out_dir / "timings.json", timings)
        ctx.checkpoint()
    positions = state["positions"].numpy()
    params = shape_params_summary(state["shape_state"], cfg, scene)
    return RunOutcome(out_dir, positions, state["texture"].numpy(), params, timings)


def held_vertices(anchor_log10, h: float) -> dict:
    """The soft anchors in params.json: the vertices they hold (w h² > 1, the spring outweighs the inertia
    within a substep) and each anchor's stiffness per unit mass."""
    w = 10.0 ** np.asarray(anchor_log10, dtype=np.float64)
    return {"held_vertices": [int(i) for i in np.flatnonzero(w * h * h > 1.0)],
            "anchor_stiffness": [float(v) for v in w]}


def shape_params_summary(shape_state: dict, cfg: SaftConfig, scene: Scene) -> dict:
    """params.json from the shape state's checkpoint dict (its damping: the run's, physics.swing_damping's choice)."""
    p, damping = shape_state["params"], shape_state.get("damping")
    lY, lB, lS = (float(p[k]) for k in ("log10_Y", "log10_B", "log10_S"))
    return {
        "Y": 10 ** lY, "B": 10 ** lB, "S": 10 ** lS, "log10_Y": lY, "log10_B": lB, "log10_S": lS,
        "constant_acceleration": [float(v) for v in p["const_accel"]],
        **({"light": [float(v) for v in p["light"]]} if "light" in p else {}),
        **({"air_drag": 10 ** float(p["log10_drag"])} if "log10_drag" in p else {}),
        **(held_vertices(p["anchor_log10"], scene.frame_dt / cfg.physics.substeps) if "anchor_log10" in p else {}),
        "damping": cfg.physics.damping if damping is None else damping, "density": cfg.physics.density,
        "frame_dt": scene.frame_dt, "substeps": cfg.physics.substeps,
        "units": {"Y": "N/m", "B": "N·m/rad²", "S": "N·m/rad²", "constant_acceleration": "m/s²", "air_drag": "kg/m³",
                  "forces.npy": "per-vertex accelerations, m/s², shape (frames-1, vertices, 3)"},
    }
