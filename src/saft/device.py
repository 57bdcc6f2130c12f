"""Where torch runs: the device a run asks for, per part of the run, and how many CPU threads torch uses.

A run has three parts that may go to different devices (``plan_devices``):

    physics      the cloth simulation of the shape phase (float64; numba on the CPU, torch on CUDA)
    render       the differentiable rasterizer of the texture and shape phases (nvdiffrast or torch)
    appearance   Mitsuba's differentiable ray tracing of phase 3 (llvm_ad_rgb or cuda_ad_rgb)

``--device cpu`` and ``--device cuda`` put every part there. ``--device auto`` puts each part where it was
measured fastest (BENCHMARKS.md, "GPU"), and the plan states why in the log and in ``saft info``.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field

import torch

from saft.appearance.mitsuba_backend import ensure_backend
from saft.errors import BackendUnavailableError, SaftInputError
from saft.render.nvdiffrast_backend import nvdiffrast_status

# The cloth simulation on CUDA (dense-factor CG, saft.physics.solver_dense) against the CPU's (numba kernels,
# ILU-preconditioned CG), R1's 32x32 template, 50 frames forward + backward, on one H200 machine
# (BENCHMARKS.md, "GPU"): 0.61 s against 1.32 s. Its cost grows with the dense factor (n^2 memory, n^3 per
# factorisation), so `auto` puts the physics on CUDA up to this many vertices (64x64: a 600 MB float32
# inverse, a factorisation about 64 times R1's 6 ms), and on the CPU above.
PHYSICS_CUDA_MAX_VERTICES = 4096
# For A/B runs on a GPU machine (benchmarks/gpu_check.sh): "cpu" or "cuda" overrides auto's physics device.
ENV_PHYSICS_DEVICE = "SAFT_PHYSICS_DEVICE"


def resolve_device(name: str) -> torch.device:
    """'auto' (CUDA when torch sees it, else CPU), 'cpu' or 'cuda'; 'cuda' without a CUDA device is an input error.
    The device of the renders; plan_devices says where each part of a run goes."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SaftInputError("--device", "cuda was asked for but torch sees no CUDA device")
    return torch.device(name)


@dataclass(frozen=True)
class DevicePlan:
    """The device of each part of a run, and one line per part saying why."""
    physics: torch.device
    render: torch.device
    appearance: torch.device
    why: dict = field(default_factory=dict, compare=False)

    def lines(self) -> list[str]:
        return [f"{part:<10} {getattr(self, part).type:<4}  {self.why.get(part, '')}"
                for part in ("physics", "render", "appearance")]


def plan_devices(name: str, *, vertices: int | None = None, appearance: bool = True, rasterizer: str = "auto",
                 nvdiffrast_ok: bool | None = None, mitsuba_cuda_ok: bool | None = None) -> DevicePlan:
    """Per-part devices for run.device = `name` ('auto', 'cpu' or 'cuda').

    vertices: the template's vertex count (None: a template of R1's size), for the physics' device.
    rasterizer: the run's render.backend ('auto', 'torch' or 'nvdiffrast'), named in the renders' line.
    appearance: whether the run has an appearance phase (else Mitsuba is not probed and the part stays on
    the CPU). nvdiffrast_ok / mitsuba_cuda_ok: whether those backends work on this machine's GPU; None =
    probe them (only when a CUDA device is there: nvdiffrast rasterizes a triangle, Mitsuba renders in a
    subprocess).
    """
    render = resolve_device(name)
    cpu = torch.device("cpu")
    if render.type == "cpu":
        why = "asked for (--device cpu)" if name == "cpu" else "no CUDA device"
        return DevicePlan(cpu, cpu, cpu, {p: why for p in ("physics", "render", "appearance")})
    if nvdiffrast_ok is None and rasterizer != "torch":
        nvdiffrast_ok = nvdiffrast_status()[0]
    if mitsuba_cuda_ok is None:
        mitsuba_cuda_ok = appearance and _mitsuba_cuda_ok()
    raster = ("the PyTorch rasterizer (render.backend = torch)" if rasterizer == "torch" else "nvdiffrast"
              if nvdiffrast_ok else "the PyTorch rasterizer (nvdiffrast not usable)")
    if name == "cuda":
        return DevicePlan(render, render, render, {
            "physics": "asked for (--device cuda); torch solver",
            "render": f"asked for (--device cuda); {raster}",
            "appearance": "asked for (--device cuda); Mitsuba cuda_ad_rgb"
                          + ("" if mitsuba_cuda_ok else " (not usable here: the phase will say why)")})
    forced = os.environ.get(ENV_PHYSICS_DEVICE, "")
    small = (vertices or 1024) <= PHYSICS_CUDA_MAX_VERTICES
    on_cuda = forced == "cuda" if forced in ("cpu", "cuda") else small
    physics = render if on_cuda else cpu
    size = f"{vertices} vertices" if vertices else "templates"
    why = {
        "physics": (f"{physics.type.upper()}: set by {ENV_PHYSICS_DEVICE}" if forced in ("cpu", "cuda") else
                    f"CUDA, dense-factor CG: faster than the CPU's for {size} up to {PHYSICS_CUDA_MAX_VERTICES}"
                    if on_cuda else
                    f"CPU, numba + ILU-preconditioned CG: the dense CUDA solver is for up to "
                    f"{PHYSICS_CUDA_MAX_VERTICES} vertices"),
        "render": f"CUDA, {raster}: measured faster than the CPU rasterizer",
        "appearance": ("CUDA, Mitsuba cuda_ad_rgb" if mitsuba_cuda_ok else
                       "CPU, Mitsuba llvm_ad_rgb: Mitsuba's CUDA variant is not usable here" if appearance else
                       "no appearance phase in this run"),
    }
    return DevicePlan(physics, render, render if mitsuba_cuda_ok else cpu, why)


def appearance_device(name: str) -> torch.device:
    """The appearance phase's device for run.device = `name` (what plan_devices says, without the rasterizer
    probe): CUDA when asked for, or with 'auto' when Mitsuba's CUDA variant works here; else the CPU."""
    return plan_devices(name, rasterizer="torch").appearance


@functools.cache
def _mitsuba_cuda_ok() -> bool:
    try:
        ensure_backend("cuda")
    except (BackendUnavailableError, ImportError):
        return False
    return True


def cpu_threads(requested: int) -> int:
    """Threads for torch on the CPU. 0 = automatic: 1 on machines with ≤ 2 cores, where torch's OpenMP
    spinning collapses when another process competes for a core (measured: 11.6 s vs 1.9 s per demo epoch
    with 2 vs 1 threads on a loaded 2-core machine), else half the cores (at most 8)."""
    if requested > 0:
        return requested
    cores = os.cpu_count() or 1
    return 1 if cores <= 2 else min(8, cores // 2)


__all__ = ["DevicePlan", "appearance_device", "PHYSICS_CUDA_MAX_VERTICES", "cpu_threads", "plan_devices", "resolve_device"]
