"""Loading Mitsuba 3 safely: variant by device, a system LLVM >= 19 for the CPU variant, one-line errors.

Mitsuba's CPU variant (``llvm_ad_rgb``) JIT-compiles through the *system* LLVM shared library. Dr.Jit finds it
through ``DRJIT_LIBLLVM_PATH`` or a default lookup (``libLLVM.so``). LLVM older than 19 either is not found
or aborts the whole process while compiling a kernel ("Cannot select: f32 = fminimum"), so the first use is
probed in a *subprocess*; when the default lookup fails we look for an LLVM >= 19 on this machine and set
``DRJIT_LIBLLVM_PATH`` ourselves (before Dr.Jit is imported in this process). When nothing works, a
:class:`saft.errors.BackendUnavailableError` says in one line what to install.

The CUDA variant (``cuda_ad_rgb``) is selected for ``device="cuda"``; that path is untested on CPU-only
machines.
"""

from __future__ import annotations

import glob
import os
import re
import subprocess
import sys

from saft.errors import BackendUnavailableError

MIN_LLVM = 19
INSTALL_HINT = "apt-get install -y libllvm19"

# Probe: load the variant and render a tiny scene whose kernels use the operations old LLVMs cannot select.
_PROBE = r"""
import sys
import drjit as dr
import mitsuba as mi
mi.set_variant(sys.argv[1])
if sys.argv[1].startswith('llvm'):
    print('LLVM', '.'.join(str(v) for v in dr.detail.llvm_version()), flush=True)
scene = mi.load_dict({'type': 'scene', 'integrator': {'type': 'prb', 'max_depth': 2},
    'sensor': {'type': 'perspective', 'film': {'type': 'hdrfilm', 'width': 4, 'height': 4}},
    'sphere': {'type': 'sphere', 'center': [0, 0, 3], 'bsdf': {'type': 'principled'}},
    'light': {'type': 'constant'}})
img = mi.render(scene, spp=1)
dr.eval(dr.minimum(img, 0.5))
print('OK', flush=True)
"""

_checked: dict[str, str] = {}


def variant_for_device(device) -> str:
    """``llvm_ad_rgb`` for a CPU device, ``cuda_ad_rgb`` for a CUDA device (str or torch.device)."""
    kind = getattr(device, "type", None) or str(device or "cpu").split(":")[0]
    if kind == "cuda":
        return "cuda_ad_rgb"
    if kind == "cpu":
        return "llvm_ad_rgb"
    raise ValueError(f"no Mitsuba variant for device {device!r}")


def _llvm_version_of(path: str) -> tuple[int, ...] | None:
    """Version from a library file name such as libLLVM-19.so, libLLVM.so.19.1, llvm-19/lib/libLLVM.so."""
    real = os.path.realpath(path)
    for name in (os.path.basename(real), os.path.basename(path), real, path):
        m = re.search(r"libLLVM[-.](?:so\.)?(\d+)(?:\.(\d+))?", name) or re.search(r"llvm-(\d+)", name)
        if m:
            return tuple(int(g) for g in m.groups() if g is not None)
    return None


def find_llvm_candidates(min_major: int = MIN_LLVM) -> list[str]:
    """Paths of LLVM shared libraries of version >= `min_major` on this machine, newest first."""
    patterns = [
        "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
        "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
        "/usr/lib/llvm-*/lib/libLLVM*.so*",
        "/usr/lib64/libLLVM*.so*",
        "/usr/local/lib/libLLVM*.so*",
        "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
        "/usr/local/opt/llvm/lib/libLLVM*.dylib",
    ]
    if os.environ.get("CONDA_PREFIX"):
        patterns.append(os.path.join(os.environ["CONDA_PREFIX"], "lib", "libLLVM*.so*"))
    found: dict[str, tuple[int, ...]] = {}
    for pat in patterns:
        for path in glob.glob(pat):
            ver = _llvm_version_of(path)
            if ver and ver[0] >= min_major and os.path.isfile(path):
                found.setdefault(os.path.realpath(path), ver)
    return sorted(found, key=lambda p: found[p], reverse=True)


def _probe(variant: str, env: dict, timeout: float = 120.0) -> tuple[bool, str]:
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE, variant], env=env, capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, "timed out"
    out = proc.stdout + proc.stderr
    return proc.returncode == 0 and "OK" in proc.stdout, out


def _explain(variant: str, out: str, llvm_path: str | None) -> str:
    if variant.startswith("cuda"):
        last = out.strip().splitlines()[-1] if out.strip() else "unknown error"
        return f"Mitsuba's CUDA variant cannot be loaded ({last[:160]}); install an NVIDIA driver and `pip install mitsuba`"
    if "No module named" in out:
        return "Mitsuba 3 is not installed: pip install 'mitsuba>=3.6'"
    m = re.search(r"LLVM (\d+)\.", out)
    ver = int(m.group(1)) if m else (_llvm_version_of(llvm_path)[0] if llvm_path and _llvm_version_of(llvm_path) else None)
    where = f" ({llvm_path})" if llvm_path else ""
    if ver is not None and ver < MIN_LLVM:
        return (f"Mitsuba's CPU backend needs LLVM >= {MIN_LLVM} but found LLVM {ver}{where}: "
                f"{INSTALL_HINT} (or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= {MIN_LLVM})")
    return (f"Mitsuba's CPU backend cannot load a system LLVM >= {MIN_LLVM}{where}: "
            f"{INSTALL_HINT} (or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= {MIN_LLVM})")


def ensure_backend(device="cpu") -> str:
    """Check that Mitsuba can render with the variant for `device`; return the variant name.

    On CPU, when the default LLVM lookup fails (or finds an LLVM < 19) and the user did not set
    DRJIT_LIBLLVM_PATH, an LLVM >= 19 found on this machine is put into DRJIT_LIBLLVM_PATH. The check runs
    once per process in a subprocess (an old LLVM aborts the process rather than raising). Raises
    BackendUnavailableError with a one-line message naming what to install.
    """
    variant = variant_for_device(device)
    if variant in _checked:
        return variant
    env = dict(os.environ)
    user_path = env.get("DRJIT_LIBLLVM_PATH")
    ok, out = _probe(variant, env)
    if not ok and variant.startswith("llvm") and not user_path:
        for cand in find_llvm_candidates():
            env["DRJIT_LIBLLVM_PATH"] = cand
            ok, out2 = _probe(variant, env)
            if ok:
                os.environ["DRJIT_LIBLLVM_PATH"] = cand
                break
    if not ok:
        raise BackendUnavailableError(_explain(variant, out, user_path))
    _checked[variant] = env.get("DRJIT_LIBLLVM_PATH", "")
    return variant


def load_mitsuba(device="cpu"):
    """Check the backend (see ensure_backend), set the variant and return the ``mitsuba`` module."""
    variant = ensure_backend(device)
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi
