"""Per-substep element kernels of the rollout, fused into two functions, optionally ``torch.compile``d.

``step_forward``: dE/dx and the data of A = M + h^2 K at one configuration.
``step_adjoint``: everything the adjoint of one substep needs from the elements besides the linear solve:
the position adjoint increment -h (d2E/dx2) lam - h^2 d/dx (lam^T K(x) v1) and the stiffness gradients.

Both are plain torch on top of ``ElementEval``. With ``SAFT_PHYSICS_COMPILE=1`` (or ``compile=True``) they
run through ``torch.compile`` (inductor): about 2-4x less time per substep on CPU, at the price of a
one-off compilation per mesh size (tens of seconds on a loaded 2-core machine, cached on disk by
inductor afterwards) - worth it for a long reconstruction, not for short runs or the test suite, so it
is off by default. Any compilation failure (no C++ compiler, unsupported platform) falls back to eager
with one warning. Stiffnesses and step sizes are passed as 0-dim tensors so new parameter values do not
trigger recompilation. Only the "projected" Hessian mode is compiled; "exact" always runs eagerly.
"""

from __future__ import annotations

import os
import warnings

import torch

from saft.physics.energy import ElementEval
from saft.physics.topology import _FAST_MAP_FIELDS

ENV_COMPILE = "SAFT_PHYSICS_COMPILE"


class _Geo:
    """The tensors of a ClothTopology that ElementEval reads (a plain object dynamo can trace)."""

    __slots__ = ("edges", "rest_len", "hinges", "rest_angle", "bend_w", "scatter_idx", "spring_idx",
                 "hinge_idx", "diag_idx", "hinge_idx_outer", *_FAST_MAP_FIELDS, "nnz", "nnz_up")


_GEO_FIELDS = _Geo.__slots__[:-2]


def _geo(nnz, tensors):
    g = _Geo()
    for name, val in zip(_GEO_FIELDS, tensors):
        setattr(g, name, val)
    g.nnz = nnz
    g.nnz_up = (nnz + g.diag_up_idx.shape[0]) // 2  # as ClothTopology.nnz_up
    return g


def _step_forward(mode, nnz, x, Y, B, S, hh, mass_diag, diag_idx, *geo):
    ev = ElementEval(_geo(nnz, geo), x, Y, B, S, mode)
    return ev.grad().T, ev.system_values(hh, mass_diag)


def _step_adjoint(mode, nnz, x, lam, v1, Y, B, S, h, *geo):
    ev = ElementEval(_geo(nnz, geo), x, Y, B, S, mode)
    parts, gY, hc = ev.adjoint_increment(lam.T, v1.T, h)
    bw = ev.t.bend_w
    return ev.scatter(parts).T, gY, (hc * bw).sum(), (hc * (1.0 - bw)).sum()


_compiled: dict = {}
_compile_failed = False


def compile_requested(flag: bool | None = None) -> bool:
    if flag is not None:
        return bool(flag)
    return os.environ.get(ENV_COMPILE, "0").strip().lower() in ("1", "true", "yes", "on")


class StepKernels:
    """The two fused kernels for one topology and Hessian mode, eager or compiled."""

    def __init__(self, topology, mode: str, compile: bool | None = None):
        t = topology
        self.mode = mode
        self.nnz = t.nnz
        self.geo = tuple(getattr(t, name) for name in _GEO_FIELDS)
        self.use_compile = compile_requested(compile) and mode == "projected" and not _compile_failed

    def _call(self, name, fn, *args):
        global _compile_failed
        if self.use_compile and not _compile_failed:
            try:
                cf = _compiled.get(name)
                if cf is None:
                    cf = _compiled[name] = torch.compile(fn, dynamic=False)
                return cf(self.mode, self.nnz, *args, *self.geo)
            except Exception as exc:  # noqa: BLE001 - any compiler problem: stay correct, run eagerly
                _compile_failed = True
                warnings.warn(f"saft.physics: torch.compile of the element kernels failed ({exc!r:.200}); "
                              "running them eagerly", RuntimeWarning, stacklevel=3)
        return fn(self.mode, self.nnz, *args, *self.geo)

    def forward(self, x, Y, B, S, hh, mass_diag, diag_idx):
        """(dE/dx as (V, 3), A data (nnz,)) at positions x."""
        return self._call("fwd", _step_forward, x, Y, B, S, hh, mass_diag, diag_idx)

    def adjoint(self, x, lam, v1, Y, B, S, h):
        """(position-adjoint increment (V, 3), d/dY, d/dB, d/dS pieces (0-dim, times the stiffness))."""
        return self._call("adj", _step_adjoint, x, lam, v1, Y, B, S, h)
