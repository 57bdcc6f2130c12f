"""The pipeline: Scene → texture phase → shape phase → (appearance phase) → result folder.

It only sequences the phases, checkpoints between epochs, and writes the results; the phases themselves
live in their own modules and do not reach into each other.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from saft.config_io import to_toml
from saft.errors import SaftInputError
from saft.io_utils import atomic_write_text
from saft.reconstruct.checkpoint import (CheckpointClock, InterruptGuard, Interrupted, load_checkpoint,
                                         save_checkpoint)
from saft.reconstruct.config import SaftConfig
from saft.reconstruct.context import PhaseContext, to_device_targets
from saft.reconstruct.progress import EpochLog, Progress
from saft.reconstruct.shape_phase import (ShapeSimulator, initial_const_accel, new_shape_state,
                                          restore_shape_state, run_shape_phase)
from saft.reconstruct.texture_phase import new_texture_state, restore_texture_state, run_texture_phase
from saft.scene import Scene

log = logging.getLogger("saft")

CHECKPOINT_VERSION = 1


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SaftInputError("--device", "cuda was asked for but torch sees no CUDA device")
    return torch.device(name)


def cpu_threads(requested: int) -> int:
    """Threads for torch on the CPU. 0 = automatic: 1 on machines with ≤ 2 cores, where torch's OpenMP
    spinning collapses when another process competes for a core (measured: 11.6 s vs 1.9 s per demo epoch
    with 2 vs 1 threads on a loaded 2-core machine), else half the cores (at most 8)."""
    import os

    if requested > 0:
        return requested
    cores = os.cpu_count() or 1
    return 1 if cores <= 2 else min(8, cores // 2)


@dataclass
class RunOutcome:
    out_dir: Path
    positions: np.ndarray                  # (N, V, 3) world frame
    texture: np.ndarray                    # (S, S, 3) sRGB
    params: dict
    timings: dict = field(default_factory=dict)


def reconstruct(scene: Scene, cfg: SaftConfig, out_dir: str | Path, *, resume: bool = False, quiet: bool = False,
                on_epoch: Callable[[str, int], None] | None = None) -> RunOutcome:
    """Run every enabled phase on `scene` and write the result folder `out_dir` (layout: saft.result).

    `on_epoch(phase, epochs_done)` is called after every epoch; returning True acts like Ctrl-C. Ctrl-C
    stops at the end of the current epoch after writing the checkpoint (KeyboardInterrupt is raised then),
    and `resume=True` continues from it.
    """
    out_dir = Path(out_dir)
    device = resolve_device(cfg.run.device)
    if cfg.appearance.profile == "auto":   # programmatic use; the CLI resolves it in load_saft_config
        from dataclasses import replace

        from saft.appearance import profile_for_device

        cfg = replace(cfg, appearance=profile_for_device(device, replace(cfg.appearance, profile="paper")))
    torch.set_num_threads(cpu_threads(cfg.run.threads))
    torch.manual_seed(cfg.run.seed)
    np.random.seed(cfg.run.seed)

    saved = load_checkpoint(out_dir) if resume else None
    if resume and saved is None:
        log.warning("no checkpoint in %s: starting from the beginning", out_dir)
    if saved is not None and saved.get("version") != CHECKPOINT_VERSION:
        raise SaftInputError(out_dir / "checkpoint", "checkpoint from another saft version; remove it to restart")
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "config.toml", to_toml(cfg))

    # ---------------------------------------------------------------- shared context
    from saft.render import get_rasterizer

    camera = scene.working_camera(cfg.render.scale)
    frames = scene.working_frames(cfg.render.scale)
    t_load = time.perf_counter()
    rgb, mask = frames.load()
    target_rgb, target_mask = to_device_targets(rgb, mask, device)
    template = torch.as_tensor(scene.template.vertices, dtype=torch.float64, device=device)
    progress = Progress(quiet=quiet)
    epoch_log = EpochLog(saved["log"] if saved else None)
    timings: dict = dict(saved["timings"]) if saved else {}
    timings["load_frames"] = timings.get("load_frames", 0.0) + time.perf_counter() - t_load
    guard = InterruptGuard()
    clock = CheckpointClock(cfg.run.checkpoint_seconds)
    state: dict = saved or {"version": CHECKPOINT_VERSION, "phase": "texture"}

    def write_checkpoint() -> None:
        state["log"] = epoch_log.rows
        state["timings"] = timings
        save_checkpoint(out_dir, state)
        clock.mark()

    def epoch_done(phase: str, epochs_done: int, state_fn) -> None:
        if on_epoch is not None and on_epoch(phase, epochs_done):
            guard.requested = True
        if guard.requested or clock.due():
            state[f"{phase}_state"] = state_fn()
            write_checkpoint()
        if guard.requested:
            raise Interrupted(f"interrupted in phase {phase} after epoch {epochs_done}; "
                              f"continue with --resume (checkpoint in {out_dir / 'checkpoint'})")

    ctx = PhaseContext(
        device=device, camera=camera, template_positions=template,
        triangles=torch.as_tensor(scene.template.triangles, dtype=torch.int32, device=device),
        uvs=torch.as_tensor(scene.template.uvs, dtype=torch.float32, device=device),
        target_rgb=target_rgb, target_mask=target_mask,
        rasterizer=get_rasterizer(cfg.render.backend, device), progress=progress, log=epoch_log,
        on_epoch=epoch_done,
    )

    with guard.active():
        try:
            # ------------------------------------------------------------ phase 1: texture
            t0 = time.perf_counter()
            if state["phase"] == "texture":
                if cfg.texture.enabled:
                    ts = (restore_texture_state(cfg.texture, state["texture_state"], device)
                          if "texture_state" in state else new_texture_state(cfg.texture, scene.texture, device))
                    texture = run_texture_phase(ctx, cfg.texture, ts)
                else:
                    from saft.reconstruct.texture_phase import initial_texture

                    texture = initial_texture(cfg.texture, scene.texture, device)
                state.pop("texture_state", None)
                state["texture"] = texture.cpu()
                state["phase"] = "shape"
                timings["texture"] = timings.get("texture", 0.0) + time.perf_counter() - t0
                write_checkpoint()
            texture = state["texture"].to(device)

            # ------------------------------------------------------------ phase 2: shape
            t0 = time.perf_counter()
            sim = ShapeSimulator(template, scene.template.quads, cfg.physics, scene.frame_dt, scene.pinned)
            if state["phase"] == "shape":
                ss = (restore_shape_state(state["shape_state"], cfg.shape, device) if "shape_state" in state
                      else new_shape_state(scene.num_frames, scene.template.num_vertices,
                                           initial_const_accel(scene.gravity_or_default(), scene.pinned, cfg.shape),
                                           cfg.physics, cfg.shape, device))
                if cfg.shape.enabled:
                    positions = run_shape_phase(ctx, sim, ss, cfg.physics, cfg.shape, texture)
                else:
                    with torch.no_grad():
                        positions = sim.simulate(ss.params, scene.num_frames)
                state["shape_state"] = ss.state_dict()
                state["positions"] = positions.detach().cpu()
                state["phase"] = "outputs"
                timings["shape"] = timings.get("shape", 0.0) + time.perf_counter() - t0
                write_checkpoint()
        except Interrupted as exc:
            progress.end_phase()
            epoch_log.write(out_dir / "log.csv")
            raise KeyboardInterrupt(str(exc)) from None

    positions = state["positions"]
    params = shape_params_summary(state["shape_state"]["params"], cfg, scene)
    from saft.io_utils import atomic_write_json
    from saft.reconstruct.outputs import write_shape_outputs

    if state["phase"] == "outputs":
        t0 = time.perf_counter()
        write_shape_outputs(out_dir, scene, camera, positions.numpy(), texture, state["shape_state"]["params"],
                            params, ctx)
        timings["outputs"] = time.perf_counter() - t0
        epoch_log.write(out_dir / "log.csv")
        atomic_write_json(out_dir / "timings.json", timings)
        state["phase"] = "appearance" if cfg.appearance.enabled else "done"
        write_checkpoint()

    # ---------------------------------------------------------------- phase 3: appearance
    if state["phase"] == "appearance":
        from saft.reconstruct.appearance_outputs import run_appearance_phase, write_appearance_renders

        t0 = time.perf_counter()

        def appearance_checkpoint(app_state: dict) -> None:
            state["appearance_state"] = app_state
            write_checkpoint()

        def check_interrupt() -> None:
            if guard.requested:
                raise Interrupted("interrupted in phase appearance; continue with --resume "
                                  f"(checkpoint in {out_dir / 'checkpoint'})")

        with guard.active():
            try:
                result = run_appearance_phase(
                    out_dir, positions.numpy(), scene.template.triangles, scene.template.uvs, camera, rgb, mask,
                    cfg.appearance, device, progress, state.get("appearance_state"), appearance_checkpoint,
                    check_interrupt, epoch_log)
            except Interrupted as exc:
                progress.end_phase()
                epoch_log.write(out_dir / "log.csv")
                raise KeyboardInterrupt(str(exc)) from None
        write_appearance_renders(out_dir, result, positions.numpy(), scene.template.triangles, scene.template.uvs,
                                 camera, rgb, device)
        timings["appearance"] = timings.get("appearance", 0.0) + time.perf_counter() - t0
        state.pop("appearance_state", None)
        state["phase"] = "done"
        epoch_log.write(out_dir / "log.csv")
        atomic_write_json(out_dir / "timings.json", timings)
        write_checkpoint()
    return RunOutcome(out_dir, positions.numpy(), texture.cpu().numpy(), params, timings)


def shape_params_summary(p: dict, cfg: SaftConfig, scene: Scene) -> dict:
    lY, lB, lS = (float(p[k]) for k in ("log10_Y", "log10_B", "log10_S"))
    return {
        "Y": 10 ** lY, "B": 10 ** lB, "S": 10 ** lS, "log10_Y": lY, "log10_B": lB, "log10_S": lS,
        "constant_acceleration": [float(v) for v in p["const_accel"]],
        "damping": cfg.physics.damping, "density": cfg.physics.density, "frame_dt": scene.frame_dt,
        "substeps": cfg.physics.substeps,
        "units": {"Y": "N/m", "B": "N·m/rad²", "S": "N·m/rad²", "constant_acceleration": "m/s²",
                  "forces.npy": "per-vertex accelerations, m/s², shape (frames-1, vertices, 3)"},
    }
