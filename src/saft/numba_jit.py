"""numba compilation as saft's hand-written CPU kernels use it (physics.kernels_numba, render.torch.texture_numba)."""

from __future__ import annotations

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
