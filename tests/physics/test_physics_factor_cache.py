"""Factors kept across rollouts (saft.physics.factor_cache): same results to the solver tolerance, fewer
factorisations from the second rollout on, and a cache restored from its state dict decides as the original."""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import grid_mesh  # noqa: E402

from saft.physics import ClothTopology, PhysicsParams, rollout  # noqa: E402
from saft.physics.factor_cache import FactorCache  # noqa: E402

FRAMES = 12


def _case(scale: float = 1.0):
    v, q = grid_mesh(12, size=0.4, plane="xy")  # hanging from its top row: tension, the matrix drifts fast
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(0)
    wind = scale * 10.0 * torch.randn(FRAMES - 1, t.num_vertices, 3, generator=g, dtype=torch.float64)
    p = PhysicsParams.default(FRAMES, t.num_vertices)
    p.log10_Y = torch.tensor(1.5, dtype=torch.float64)  # a soft cloth, as the reconstructions learn
    p.log10_B = torch.tensor(-4.0, dtype=torch.float64)
    p.a_vert = wind.requires_grad_(True)
    return t, p, list(range(13))


def _run(t, p, top, cache=None, first_step=0, frames=FRAMES, x0=None, solver="auto"):
    stats = {}
    x = rollout(t, t.template if x0 is None else x0, None, p, num_frames=frames, pinned=top, stats=stats,
                factor_cache=cache, first_step=first_step, solver=solver)
    x.pow(2).sum().backward()
    return x.detach(), p.a_vert.grad.clone(), stats


def test_cached_factors_give_the_same_motion_and_gradients_with_fewer_factorisations():
    t, p, top = _case()
    x_ref, g_ref, s_ref = _run(t, p, top)
    cache = FactorCache()
    t, p, top = _case()
    x1, g1, s1 = _run(t, p, top, cache)
    assert len(cache) > 0 and cache.nbytes == sum(FactorCache.entry_nbytes(e[2]) for e in cache.entries.values())
    # the next epoch: slightly other forces, the cache from the last one
    t, p2, top = _case(1.01)
    x2, g2, s2 = _run(t, p2, top, cache)
    x2_ref, _, s2_ref = _run(*_case(1.01))
    np.testing.assert_allclose(x1.numpy(), x_ref.numpy(), rtol=0, atol=5e-8)  # CG to 1e-6 of each right-hand side
    np.testing.assert_allclose(x2.numpy(), x2_ref.numpy(), rtol=0, atol=5e-8)  # CG to 1e-6 of each right-hand side
    np.testing.assert_allclose(g1.numpy(), g_ref.numpy(), rtol=1e-5, atol=1e-9 * float(g_ref.abs().max()))
    assert s_ref["factorizations"] > 3  # the case does refactorise without a cache
    assert s2["factorizations"] < s2_ref["factorizations"] / 2


def test_the_dense_solver_keeps_its_factors_in_the_cache_too():
    """The CUDA default (solver_dense) on the CPU: the next epoch's rollout starts from the kept dense factors
    (none made at its start) and gives the uncached rollout's motion and gradients; they are not checkpointed."""
    t, p, top = _case()
    cache = FactorCache()
    x1, g1, s1 = _run(t, p, top, cache, solver="dense")
    assert len(cache.dense) == s1["factorizations"] + s1["bwd_factorizations"] > 0 and len(cache) == 0
    t, p2, top = _case(1.01)
    x2, g2, s2 = _run(t, p2, top, cache, solver="dense")
    x2_ref, g2_ref, s2_ref = _run(*_case(1.01), solver="dense")
    np.testing.assert_allclose(x2.numpy(), x2_ref.numpy(), rtol=0, atol=5e-8)
    # float32 factors, CG to 1e-6 of each right-hand side: the gradients agree to that tolerance, not below it
    # (1e-7 held on an AMD EPYC by chance; an Intel Xeon's BLAS differs by 8e-4 relative on 1e-6-sized entries)
    np.testing.assert_allclose(g2.numpy(), g2_ref.numpy(), rtol=1e-4, atol=1e-6 * float(g2_ref.abs().max()))
    assert s2_ref["factorizations"] >= 1 and s2["factorizations"] < s2_ref["factorizations"]
    assert "dense" not in str(cache.state_dict().keys())


def test_windowed_rollouts_key_the_cache_by_absolute_substep():
    t, p, top = _case()
    cache = FactorCache()
    x, _, _ = _run(t, p, top, cache, frames=FRAMES)
    steps = set(cache.entries)
    assert min(steps) >= 0 and max(steps) < (FRAMES - 1) * 4

    def window(c):  # frames 5.. from the state at frame 5 (at rest: the velocity is not returned)
        t, p, top = _case()
        p.a_vert = p.a_vert.detach()[5:].clone().requires_grad_(True)
        return _run(t, p, top, c, first_step=5 * 4, frames=FRAMES - 5, x0=x[5])[2]

    s_cached, s_fresh = window(cache), window(None)
    assert set(cache.entries) >= {k for k in steps if k < 20}  # nothing before the window replaced or lost
    assert s_cached["factorizations"] < s_fresh["factorizations"]


def test_a_restored_cache_decides_as_the_original():
    t, p, top = _case()
    cache = FactorCache()
    _run(t, p, top, cache)
    copy = FactorCache()
    copy.load_state_dict(cache.state_dict())
    assert list(copy.entries) == list(cache.entries) and copy.nbytes == cache.nbytes
    xa, ga, sa = _run(*_case(1.02), cache)
    xb, gb, sb = _run(*_case(1.02), copy)
    assert torch.equal(xa, xb) and torch.equal(ga, gb)
    assert sa == sb


def test_over_its_budget_the_cache_thins_out_and_keeps_its_byte_count():
    t, p, top = _case()
    full = FactorCache()
    _run(t, p, top, full)
    one = max(FactorCache.entry_nbytes(e[2]) for e in full.entries.values())
    small = FactorCache(budget_bytes=3 * one)
    x_small, _, _ = _run(*_case(), small)
    assert 0 < len(small) <= 3 and small.nbytes <= small.budget_bytes
    assert small.nbytes == sum(FactorCache.entry_nbytes(e[2]) for e in small.entries.values())
    x_ref, _, _ = _run(*_case())
    np.testing.assert_allclose(x_small.numpy(), x_ref.numpy(), rtol=0, atol=5e-8)
