"""The numba element kernels (saft.physics.kernels_numba) against the torch reference (ElementEval)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import cube_mesh, grid_mesh  # noqa: E402

from saft.physics import ClothTopology, PhysicsParams, rollout  # noqa: E402
from saft.physics.kernels import StepKernels  # noqa: E402

pytest.importorskip("numba")

F64 = dict(dtype=torch.float64)


def _rel(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-300)).item()


def _case(mesh, scale, seed):
    v, q = mesh
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(seed)
    x = scale * t.template + 0.001 * torch.randn(t.template.shape, generator=g, **F64)
    lam = torch.randn(x.shape, generator=g, **F64)
    w = torch.randn(x.shape, generator=g, **F64)
    return t, x, lam, w


@pytest.mark.parametrize("mesh", ["grid", "cube"])
@pytest.mark.parametrize("scale", [0.85, 1.0, 1.15])  # compressed (projection clamps), mixed, stretched
def test_numba_kernels_match_torch(mesh, scale):
    m = grid_mesh(7, wave=0.02) if mesh == "grid" else cube_mesh()
    t, x, lam, w = _case(m, scale, seed=int(scale * 100))
    kt = StepKernels(t, "projected", backend="torch")
    kn = StepKernels(t, "projected", backend="numba")
    assert (kt.backend, kn.backend) == ("torch", "numba")
    md = t.mass.repeat_interleave(3)
    Y, B, S, hh, h = (torch.tensor(c, **F64) for c in (200.0, 1e-3, 3e-4, 0.005**2, 0.005))
    # the projection clamps on most springs (compressed), some (mixed) or few (stretched)
    ls = (x[t.edges[:, 1]] - x[t.edges[:, 0]]).norm(dim=1)
    frac = (ls < t.rest_len).double().mean().item()
    assert {0.85: frac > 0.7, 1.0: 0.2 < frac < 0.8, 1.15: frac < 0.3}[scale], frac
    ref = kt.forward(x, Y, B, S, hh, md, t.diag_idx)
    got = kn.forward(x, Y, B, S, hh, md, t.diag_idx)
    for a, b in zip(got, ref):
        assert a.shape == b.shape and a.dtype == b.dtype
        assert _rel(a, b) < 1e-12
    # A is exactly symmetric (assembled in upper-triangle storage)
    n = 3 * t.num_vertices
    A = sp.csr_matrix((got[1].numpy(), t.csr_indices, t.csr_indptr), shape=(n, n))
    assert (A - A.T).count_nonzero() == 0
    ref = kt.adjoint(x, lam, w, Y, B, S, h)
    got = kn.adjoint(x, lam, w, Y, B, S, h)
    assert got[0].shape == ref[0].shape
    assert _rel(got[0], ref[0]) < 1e-12
    for a, b in zip(got[1:], ref[1:]):
        assert a.dim() == 0
        assert _rel(a, b) < 1e-12


def test_backend_selection(monkeypatch):
    t, _, _, _ = _case(grid_mesh(3), 1.0, 0)
    assert StepKernels(t, "projected").backend == "numba"
    assert StepKernels(t, "exact").backend == "torch"
    assert StepKernels(t.to(dtype=torch.float32), "projected").backend == "torch"
    assert StepKernels(t, "projected", compile=True).backend == "torch"  # asked for torch.compile
    assert StepKernels(t, "projected", compile=True, backend="numba").backend == "numba"
    monkeypatch.setenv("SAFT_PHYSICS_KERNELS", "torch")
    assert StepKernels(t, "projected").backend == "torch"
    assert StepKernels(t, "projected", backend="auto").backend == "numba"
    monkeypatch.setenv("SAFT_PHYSICS_KERNELS", "bogus")
    with pytest.raises(ValueError, match="backend"):
        StepKernels(t, "projected")


@pytest.mark.parametrize("pinned", [None, [0, 3, 5]])
def test_rollout_numba_matches_torch(pinned):
    """Forward positions and every gradient of a rollout agree between the two kernel backends."""
    N = 8
    v, q = grid_mesh(5, wave=0.02)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(3)
    x0 = t.template + 0.002 * torch.randn(t.template.shape, generator=g, **F64)
    v0 = 0.05 * torch.randn(t.template.shape, generator=g, **F64)
    p = PhysicsParams.default(N, t.num_vertices)
    p.a_vert = 0.5 * torch.randn(N - 1, t.num_vertices, 3, generator=g, **F64)
    W = torch.randn(N, t.num_vertices, 3, generator=g, **F64)
    res = {}
    for backend in ("torch", "numba"):
        pp = PhysicsParams(*(a.detach().clone().requires_grad_(True) for a in p.tensors()))
        xx, vv = x0.clone().requires_grad_(True), v0.clone().requires_grad_(True)
        pos = rollout(t, xx, vv, pp, num_frames=N, tol=1e-13, pinned=pinned, kernels=backend)
        (pos * W).sum().backward()
        res[backend] = [pos.detach(), xx.grad, vv.grad] + [a.grad for a in pp.tensors()]
    for a, b in zip(res["numba"], res["torch"]):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * b.abs().max().item())


def test_without_numba_falls_back_to_torch(monkeypatch):
    """If numba cannot be loaded the torch kernels run, with one warning."""
    import saft.physics.kernels as K

    def broken():
        raise ImportError("no numba here")

    monkeypatch.setattr(K.kernels_numba, "load", broken)
    monkeypatch.setattr(K, "_numba_failed", False)
    t, _, _, _ = _case(grid_mesh(3), 1.0, 0)
    with pytest.warns(RuntimeWarning, match="numba element kernels unavailable"):
        assert StepKernels(t, "projected").backend == "torch"
    assert StepKernels(t, "projected").backend == "torch"  # no second warning needed, still torch


def test_nan_inside_the_numba_path_raises(monkeypatch):
    """A NaN from the numba forward kernel (third substep of frame 1) is caught like the torch path's."""
    from saft.errors import SimulationError
    from saft.physics import kernels_numba

    N = 4
    v, q = grid_mesh(4, wave=0.02)
    t = ClothTopology.from_quads(v, q)
    kernels_numba.load()
    orig = kernels_numba.step_forward
    calls = {"n": 0}

    def poisoned(*args):
        calls["n"] += 1
        g = orig(*args)
        return g * float("nan") if calls["n"] == 4 + 3 else g

    monkeypatch.setattr(kernels_numba, "step_forward", poisoned)
    with pytest.raises(SimulationError, match=r"frame 1, substep 2"):
        rollout(t, t.template, None, PhysicsParams.default(), num_frames=N, kernels="numba")
    assert calls["n"] == 4 + 3
