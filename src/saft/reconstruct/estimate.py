"""Before the first epoch: how long the texture and shape phases will take and how much memory they need.

Measured, not guessed: one render of frame 0 and one simulation substep of the template pulled by gravity
(forward + backward, reusing the factorisation of an untimed first substep, as the run's substeps mostly do)
are timed on the run's own device, and the bytes autograd keeps for them are counted. A substep of a cloth
in fast motion can be dearer (more solver iterations, a refactorisation now and then): take the estimate as
good to a factor of two. The phases repeat these
steps a known number of times (the epoch schedule), so

    time   ≈ texture epochs · t_render + Σ_shape epochs (frames · t_render + (frames − 1) · t_transition)
    memory ≈ targets + (frames − 1) · graph per transition + min(frames, render chunk) · graph per render

(frames: those the epoch simulates; in the windowed epochs of shape.window, fewer than those in use).

The appearance phase (Mitsuba) is not included. A large template or an estimate above the machine's
memory is warned about.
"""

from __future__ import annotations

import logging
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from saft.physics import PhysicsParams, rollout
from saft.physics.factor_cache import FactorCache
from saft.reconstruct.config import SaftConfig
from saft.reconstruct.frame_schedule import simulated_frames_per_epoch
from saft.reconstruct.frame_renders import render_chunk

log = logging.getLogger("saft")

LARGE_TEMPLATE = 10_000          # vertices: warn above this
LONG_RUN_SECONDS = 3600.0        # warn above an hour


@dataclass
class RunEstimate:
    seconds: float                  # texture + shape phases
    peak_bytes: int
    render_seconds: float           # one frame, forward + backward
    transition_seconds: float       # one frame transition of the simulation, forward + backward


@contextmanager
def _count_saved_bytes(counter: list[int]):
    """Sum the sizes of the tensors autograd saves for backward while the block runs."""
    def pack(t):
        counter[0] += t.numel() * t.element_size()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        yield


def _timed(fn) -> tuple[float, int]:
    """(seconds, saved bytes) of fn() followed by its backward (once: costs of a fresh call count, as they
    recur in the run, e.g. the solver's factorisation whenever the stiffnesses change)."""
    counter = [0]
    t0 = time.perf_counter()
    with _count_saved_bytes(counter):
        loss = fn()
    loss.backward()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()   # the time of the GPU's work, not of its launch
    return time.perf_counter() - t0, counter[0]


def measure_run(ctx, sim, cfg: SaftConfig, num_frames: int, gravity) -> RunEstimate:
    device = ctx.device
    texture = torch.full((cfg.texture.size, cfg.texture.size, 3), 0.5, device=device, requires_grad=True)
    verts = ctx.template_positions.to(torch.float32)[None].requires_grad_(True)

    def render():
        return ctx.render(verts, texture).rgb.square().mean()

    # untimed first: CUDA's first launches (context, kernels, cuBLAS) cost seconds once; R1's estimate on an
    # H200 was 72 min for a run of 5.4 min before this warm-up
    render().backward()
    t_render, b_render = _timed(render)

    # One substep of a cloth pulled by gravity (a cloth at rest would make the solver's work trivial),
    # with a fresh factorisation: an upper estimate of a substep of the run. On the physics' device.
    device = sim.template.device
    dtype, V = sim.template.dtype, sim.template.shape[0]
    phys = cfg.physics

    def scalar(v):
        return torch.tensor(float(v), dtype=dtype, device=device, requires_grad=True)

    params = PhysicsParams(log10_Y=scalar(phys.log10_Y_init), log10_B=scalar(phys.log10_B_init),
                           log10_S=scalar(phys.log10_S_init), damping=torch.tensor(phys.damping, dtype=dtype, device=device),
                           a_const=torch.as_tensor(gravity, dtype=dtype, device=device),
                           a_vert=torch.zeros(1, V, 3, dtype=dtype, device=device, requires_grad=True))
    # The timed substep reuses the factor the untimed one made, as the run's substeps do (factors are kept
    # across epochs, physics/factor_cache.py): timing a fresh factorisation made R1's estimate 16 min on the
    # CPU for a run of 7.5 min, and a factorisation is ~6 times a whole substep on an H100.
    factors = FactorCache()

    def substep():
        return rollout(sim.topology, sim.template, None, params, num_frames=2, substeps=1,
                       frame_dt=sim.frame_dt / phys.substeps, pinned=sim.pinned, hessian=phys.hessian,
                       factor_cache=factors)[1].square().sum()

    # untimed first: the CPU kernels are compiled (numba) or loaded from their cache on first use, on CUDA
    # compiled by torch.compile, a one-off cost of seconds that would otherwise be multiplied by every substep
    substep().backward()
    t_sub, b_sub = _timed(substep)
    t_step, b_step = t_sub * phys.substeps, b_sub * phys.substeps

    texture_epochs = cfg.texture.epochs if cfg.texture.enabled else 0
    schedule = simulated_frames_per_epoch(num_frames, cfg.shape) if cfg.shape.enabled else []
    seconds = texture_epochs * t_render + sum(f * t_render + (f - 1) * t_step for f in schedule)
    seconds += num_frames * t_render   # the final renders
    targets = ctx.target_rgb.numel() * ctx.target_rgb.element_size() + ctx.target_mask.numel() * 4
    peak = targets + (num_frames - 1) * b_step + min(num_frames, render_chunk(ctx.device)) * b_render
    return RunEstimate(seconds, int(peak), t_render, t_step)


def _available_bytes(device) -> int | None:
    try:
        if getattr(device, "type", "cpu") == "cuda":
            return int(torch.cuda.mem_get_info(device)[1])
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError, RuntimeError):
        return None


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def log_estimate(ctx, sim, cfg: SaftConfig, num_frames: int, gravity) -> RunEstimate:
    """Measure (with the random state untouched) and log the estimate; warnings for large runs."""
    devices = sorted({d for d in (ctx.devices.render, ctx.devices.physics) if d.type == "cuda"}, key=str)
    with torch.random.fork_rng(devices=devices):
        est = measure_run(ctx, sim, cfg, num_frames, gravity)
    V = int(ctx.template_positions.shape[0])
    extra = " (+ appearance)" if cfg.appearance.enabled else ""
    log.info("estimate: texture + shape about %s%s, memory about %s", _duration(est.seconds), extra,
             _size(est.peak_bytes))
    log.debug("estimate from %d vertices, %d frames of %dx%d: %.3g s per render, %.3g s per simulated frame",
              V, num_frames, ctx.camera.width, ctx.camera.height, est.render_seconds, est.transition_seconds)
    available = _available_bytes(ctx.device)
    if V > LARGE_TEMPLATE:
        log.warning("large template: %d vertices (saft is tuned for up to %d); expect about %s and %s",
                    V, LARGE_TEMPLATE, _duration(est.seconds), _size(est.peak_bytes))
    if est.seconds > LONG_RUN_SECONDS and V <= LARGE_TEMPLATE:
        log.warning("this run will take about %s; Ctrl-C stops it with a checkpoint and --resume continues",
                    _duration(est.seconds))
    if available is not None and est.peak_bytes > 0.8 * available:
        log.warning("the run needs about %s but the %s has %s: it may run out of memory; lower render.scale "
                    "or use fewer frames", _size(est.peak_bytes), ctx.device.type.upper(), _size(available))
    return est


def _size(nbytes: float) -> str:
    return f"{nbytes / 1e6:.0f} MB" if nbytes < 1e9 else f"{nbytes / 1e9:.1f} GB"
