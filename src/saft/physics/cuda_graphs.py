"""CUDA graphs around the fixed-shape pieces of a substep (element kernels, blocks of CG iterations).

A substep on a cloth-sized mesh is hundreds of tiny kernels (the element adjoint alone is ~320 torch ops on
R1): launched one by one from Python they cost 5-10 us each of host time, several times the GPU's own work.
Every shape is fixed by the topology, so each piece is recorded once with ``torch.cuda.graphs`` and replayed
as one launch. ``Graphed`` records a function of static input buffers; on any other device, or where
recording fails, it calls the function directly (one code path, one warning). The arithmetic is the same
kernels either way: replaying a graph gives the bits of the eager run. With ``compile`` the function is
first ``torch.compile``d (inductor fuses the elementwise chains into a few kernels), then recorded (or, on
the CPU, called compiled); a compilation failure falls back to the eager function, with a warning.

``SAFT_PHYSICS_GRAPHS=0`` turns the recording off (eager CUDA, for A/B measurements).
"""

from __future__ import annotations

import os
import warnings

import torch

ENV_GRAPHS = "SAFT_PHYSICS_GRAPHS"
_failed = False


def graphs_wanted(device: torch.device, flag: bool | None = None) -> bool:
    """Whether to record graphs on ``device``: CUDA only; ``flag`` None reads SAFT_PHYSICS_GRAPHS (on)."""
    if device.type != "cuda" or _failed:
        return False
    if flag is not None:
        return bool(flag)
    return os.environ.get(ENV_GRAPHS, "1").strip().lower() not in ("0", "false", "no", "off")


class Graphed:
    """``fn(*inputs)`` recorded once as a CUDA graph over static copies of ``example`` inputs.

    Calling copies the new inputs into the static buffers, replays, and returns the graph's outputs - static
    buffers overwritten by the next replay, so callers that keep them must clone. An input that is the very
    tensor object given at the previous call is not copied again (the callers pass constants such as the
    stiffnesses that way; none is modified in place between calls). A function of no inputs works on buffers
    it holds itself (a CG block on its workspace). ``keep`` holds tensors the graph reads by address (the
    topology's arrays) alive as long as the graph. ``record`` False: plain calls (compiled with ``compile``)."""

    def __init__(self, fn, example=(), record: bool = True, compile: bool = False, keep=()):
        self.eager = fn
        self.fn = torch.compile(fn, dynamic=False) if compile else fn
        self.keep = keep
        self.graph = None
        self.outputs = None
        self.inputs = [a.detach().clone() for a in example] if record else []
        self.last = [None] * len(self.inputs)
        if record:
            self._record()

    def _uncompile(self, exc):
        self.fn = self.eager
        warnings.warn(f"saft.physics: torch.compile failed ({exc!r:.200}); running eagerly", RuntimeWarning,
                      stacklevel=4)

    def _record(self):
        global _failed
        fn = self.fn
        if fn is not self.eager:
            try:
                self._warm(fn)  # compiles
            except Exception as exc:  # noqa: BLE001 - any compiler problem: record the eager function
                self._uncompile(exc)
                fn = self.fn
        try:
            self._warm(fn)
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g):
                self.outputs = fn(*self.inputs)
            self.graph = g
        except Exception as exc:  # noqa: BLE001 - any capture problem: stay correct, run eagerly
            _failed = True
            self.graph = None
            warnings.warn(f"saft.physics: CUDA graph capture failed ({exc!r:.200}); running eagerly",
                          RuntimeWarning, stacklevel=3)

    def _warm(self, fn):
        """Two runs on a side stream before the capture (cuBLAS handles, the allocator, compilation)."""
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                fn(*self.inputs)
        torch.cuda.current_stream().wait_stream(side)

    def __call__(self, *args):
        if self.graph is None:
            if self.fn is not self.eager:
                try:
                    return self.fn(*args)
                except Exception as exc:  # noqa: BLE001 - any compiler problem: stay correct, run eagerly
                    self._uncompile(exc)
            return self.fn(*args)
        for k, (buf, a) in enumerate(zip(self.inputs, args)):
            if a is not self.last[k]:
                buf.copy_(a)
                self.last[k] = a
        self.graph.replay()
        return self.outputs
