"""What `saft info` reports about the optional backends: each one's version and whether saft can use it here.

    Mitsuba 3    the appearance phase (variants compiled in; the one for this machine's device is probed)
    nvdiffrast   the CUDA rasterizer (else saft's PyTorch rasterizer)
    numba        the cloth simulation's CPU kernels (element forces and Hessians, the preconditioned CG loop)
    CHOLMOD      scikit-sparse: an opt-in preconditioner of the cloth simulation (Python API, solver="cholmod")
    Ray          `saft batch`
    viser        `saft view`
"""

from __future__ import annotations

import importlib.metadata
import importlib.util

import torch

from saft.appearance.mitsuba_backend import ensure_backend
from saft.errors import BackendUnavailableError
from saft.render.nvdiffrast_backend import nvdiffrast_status


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _mitsuba() -> str:
    version = _version("mitsuba")
    if version is None:
        return "not installed (pip install mitsuba): no appearance phase"
    import mitsuba as mi

    device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        usable = f"{ensure_backend(device)} works on this machine"
    except BackendUnavailableError as exc:
        usable = f"not usable here: {exc}"
    return f"{version}, variants {', '.join(mi.variants())}; {usable}"


def _nvdiffrast() -> str:
    version = _version("diffrp-nvdiffrast") or _version("nvdiffrast")
    if importlib.util.find_spec("nvdiffrast") is None:
        return "not installed (CUDA only: pip install 'saft[cuda]'); the PyTorch rasterizer is used"
    ok, why = nvdiffrast_status()
    return f"{version or 'installed'}; " + ("works: used on CUDA" if ok else
                                            f"not usable here ({why}); the PyTorch rasterizer is used")


def _cholmod() -> str:
    if importlib.util.find_spec("sksparse") is None:
        return "not installed (optional scikit-sparse, opt-in solver='cholmod'); saft uses SuperLU"
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError as exc:
        return f"scikit-sparse installed but not importable ({exc})"
    return (f"scikit-sparse {_version('scikit-sparse') or ''}; opt-in: saft.physics.rollout(..., solver='cholmod')"
            " (saft itself uses SuperLU)").replace("  ", " ")


def _package(dist: str, purpose: str, install: str) -> str:
    version = _version(dist)
    return f"{version} ({purpose})" if version else f"not installed ({install}); {purpose} unavailable"


def backend_lines() -> list[str]:
    """One line per backend: name, version and whether saft uses it on this machine."""
    return [
        f"Mitsuba 3:  {_mitsuba()}",
        f"nvdiffrast: {_nvdiffrast()}",
        f"numba:      {_package('numba', 'the cloth simulation on the CPU', 'pip install numba')}",
        f"CHOLMOD:    {_cholmod()}",
        f"Ray:        {_package('ray', 'saft batch', 'pip install ray; install.sh installs it')}",
        f"viser:      {_package('viser', 'saft view', 'pip install viser')}",
    ]
