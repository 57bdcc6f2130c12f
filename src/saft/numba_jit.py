"""numba compilation as saft's hand-written CPU kernels use it (physics.kernels_numba, render.torch.texture_numba,
render.torch.raster_numba)."""

from __future__ import annotations

import threading

JIT_OPTIONS = dict(cache=True, fastmath=False, nogil=True)  # nopython; fastmath off: deterministic results


def jit(fn, **options):
    """numba.njit(fn) with JIT_OPTIONS and `options`, its machine code kept in numba's on-disk cache; where
    there is no writable cache location (a read-only install) it compiles in every process instead.
    Imports numba (heavy) only when called."""
    from numba import njit

    try:
        return njit(**JIT_OPTIONS, **options)(fn)
    except RuntimeError:
        return njit(**{**JIT_OPTIONS, "cache": False}, **options)(fn)


_lock = threading.Lock()


def jit_in_place(namespace: dict, kernels: tuple[str, ...], inlined: tuple[str, ...] = (), **options) -> None:
    """Replace a module's plain Python functions (`namespace`: its globals()) by numba dispatchers: the
    `inlined` helpers first (inline="always"; the kernels resolve them as globals when compiled), then the
    `kernels`, each with numba's `options` (e.g. error_model="numpy": x / 0 gives inf or nan as in torch
    instead of raising). Idempotent (the module's "_jitted" flag) and thread-safe; raises ImportError without
    numba."""
    with _lock:
        if namespace.get("_jitted"):
            return
        for name in inlined:
            namespace[name] = jit(namespace[name], inline="always", **options)
        for name in kernels:
            namespace[name] = jit(namespace[name], **options)
        namespace["_jitted"] = True
