"""Per-substep element kernels of the rollout, fused into two functions, optionally ``torch.compile``d.

``step_forward``: dE/dx and the data of A = M + h^2 K at one configuration.
``step_adjoint``: everything the adjoint of one substep needs from the elements besides the linear solve:
the position adjoint increment -h (d2E/dx2) lam - h^2 d/dx (lam^T K(x) v1) and the stiffness gradients.

Both are plain torch on top of ``ElementEval``. With ``SAFT_PHYSICS_COMPILE=1`` (or ``compile=True``) they
run through ``torch.compile`` (inductor): about 2-4x less time per substep on CPU, at the price of a
one-off compilation per mesh size (tens of seconds on a loaded 2-core machine, cached on disk by
inductor afterwards) - worth it for a long reconstruction, not for short runs or the test suite, so it
is off by default on the CPU (where numba is faster still) and on by default on CUDA (``compile_requested``).
Any compilation failure (no C++ compiler, unsupported platform) falls back to eager
with one warning. Stiffnesses and step sizes are passed as 0-dim tensors so new parameter values do not
trigger recompilation. Only the "projected" Hessian mode is compiled; "exact" always runs eagerly.

Default on the CPU: for float64 tensors in "projected" mode, ``StepKernels`` runs the hand-written numba
kernels of ``saft.physics.kernels_numba`` instead (same closed forms, equal to rounding, several times
faster than either torch path on cloth-sized meshes). On CUDA the torch kernels of the "projected" mode are
recorded once per topology as CUDA graphs (``cuda_graphs``; ~110 torch ops forward, ~320 adjoint on R1, each
replayed as one launch; ``SAFT_PHYSICS_GRAPHS=0`` turns that off). Selection (``backend`` argument, else the
``SAFT_PHYSICS_KERNELS`` environment variable): "auto" (default: numba where it applies, unless
torch.compile was asked for), "numba" (numba where it applies, torch otherwise) or "torch" (never numba;
for tests and A/B). CUDA, float32 and "exact" always use torch.
"""

from __future__ import annotations

import os
import warnings

import torch
from torch.profiler import record_function

from saft.physics import kernels_numba
from saft.physics.cuda_graphs import Graphed, graphs_wanted
from saft.physics.energy import ElementEval
from saft.physics.topology import _FAST_MAP_FIELDS

ENV_COMPILE = "SAFT_PHYSICS_COMPILE"
ENV_BACKEND = "SAFT_PHYSICS_KERNELS"
BACKENDS = ("auto", "numba", "torch")


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
_GRAPHS: dict = {}  # (kernel, mode, topology arrays) -> Graphed, for the few topologies in use


def compile_requested(flag: bool | None = None, device: torch.device | None = None) -> bool:
    """``flag``, else SAFT_PHYSICS_COMPILE where it is set, else on for CUDA: on one H100, R1's template, 50
    frames forward + backward, 0.684 s eager against 0.418 s compiled (the graphs' hundreds of tiny kernels
    fused; BENCHMARKS.md "GPU"). The CPU's default, numba, is not compiled by torch."""
    if flag is not None:
        return bool(flag)
    env = os.environ.get(ENV_COMPILE, "").strip().lower()
    if env:
        return env in ("1", "true", "yes", "on")
    return device is not None and torch.device(device).type == "cuda"


def backend_requested(backend: str | None = None) -> str:
    b = backend if backend is not None else os.environ.get(ENV_BACKEND, "auto").strip().lower() or "auto"
    if b not in BACKENDS:
        raise ValueError(f"element kernel backend must be one of {BACKENDS}, got {b!r}")
    return b


_numba_failed = False


def _numba_ready() -> bool:
    """Whether the numba kernels can run (jits them on first use; one warning if numba is unusable)."""
    global _numba_failed
    if not _numba_failed:
        try:
            kernels_numba.load()
        except Exception as exc:  # noqa: BLE001 - numba missing or broken: the torch path is always there
            _numba_failed = True
            warnings.warn(f"saft.physics: numba element kernels unavailable ({exc!r:.200}); using torch",
                          RuntimeWarning, stacklevel=3)
    return not _numba_failed


class StepKernels:
    """The two fused kernels for one topology and Hessian mode: numba (CPU float64 projected, by default),
    or torch, eager or compiled."""

    def __init__(self, topology, mode: str, compile: bool | None = None, backend: str | None = None):
        t = topology
        self.mode = mode
        self.nnz = t.nnz
        self.geo = tuple(getattr(t, name) for name in _GEO_FIELDS)
        want_compile = compile_requested(compile, t.device)
        b = backend_requested(backend)
        numba_ok = t.device.type == "cpu" and t.dtype == torch.float64 and mode == "projected"
        self.nb = None
        if numba_ok and (b == "numba" or (b == "auto" and not want_compile)) and _numba_ready():
            self.nb = kernels_numba.NumbaGeo(t)
        self.backend = "numba" if self.nb is not None else "torch"
        self.use_compile = (self.nb is None and want_compile and mode == "projected"
                            and not _compile_failed)
        # CUDA: recorded as graphs (after compilation, when that was asked for); not the "exact" mode, whose
        # hinge adjoint runs autograd (the engine's own thread) inside
        self.graphs = self.nb is None and mode == "projected" and graphs_wanted(t.device)

    def _call(self, name, fn, *args):
        global _compile_failed
        if self.graphs:
            with record_function(f"saft.kernels.{name}"):  # the phases of bench_physics.py's profile
                return self._graphed(name, fn, args)
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
        with record_function(f"saft.kernels.{name}"):
            return fn(self.mode, self.nnz, *args, *self.geo)

    def _graphed(self, name, fn, args):
        key = (name, self.mode, self.use_compile, *map(id, self.geo))  # the arrays stay alive with the graph
        g = _GRAPHS.get(key)
        if g is None:
            if len(_GRAPHS) >= 16:
                _GRAPHS.pop(next(iter(_GRAPHS)))
            mode, nnz, geo = self.mode, self.nnz, self.geo
            g = _GRAPHS[key] = Graphed(lambda *a: fn(mode, nnz, *a, *geo), args, compile=self.use_compile,
                                       keep=geo)
        return g(*args)

    def forward(self, x, Y, B, S, hh, mass_diag, diag_idx):
        """(dE/dx as (V, 3), A data (nnz,)) at positions x."""
        g = self.nb
        if g is not None:
            A = torch.empty(self.nnz, dtype=torch.float64)
            grad = kernels_numba.step_forward(
                _np(x), g.edges, g.rest_len, g.hinges, g.rest_angle, g.bend_w, g.spring_up, g.hinge_up,
                g.diag_up, g.up_of, _np(mass_diag), float(Y), float(B), float(S), float(hh), g.nnz_up,
                A.numpy())
            return torch.from_numpy(grad), A
        grad, A = self._call("fwd", _step_forward, x, Y, B, S, hh, mass_diag, diag_idx)
        # a graph's outputs are overwritten by its next replay: A may be kept for the adjoint pass (grad is used
        # at once, as are the adjoint's outputs)
        return grad, (A.clone() if self.graphs else A)

    def adjoint(self, x, lam, v1, Y, B, S, h):
        """(position-adjoint increment (V, 3), d/dY, d/dB, d/dS pieces (0-dim, times the stiffness))."""
        g = self.nb
        if g is not None:
            out, gY, gB, gS = kernels_numba.step_adjoint(
                _np(x), _np(lam), _np(v1), g.edges, g.rest_len, g.hinges, g.rest_angle, g.bend_w,
                float(Y), float(B), float(S), float(h))
            f = dict(dtype=x.dtype)
            return torch.from_numpy(out), torch.tensor(gY, **f), torch.tensor(gB, **f), torch.tensor(gS, **f)
        return self._call("adj", _step_adjoint, x, lam, v1, Y, B, S, h)


def _np(t):
    """A C-contiguous float64 numpy view (or copy) of a CPU tensor."""
    return t.detach().contiguous().numpy()
