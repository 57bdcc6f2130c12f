import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import grid_mesh, grid_system  # noqa: E402

from saft.errors import SimulationError  # noqa: E402
from saft.physics import ClothTopology, ElementEval, PhysicsParams, rollout  # noqa: E402
from saft.physics import solver as S  # noqa: E402
from saft.physics.solver import ReusedLUSolver  # noqa: E402

N = 10


def _setup(seed=0, n=4, wave=0.02):
    v, q = grid_mesh(n, wave=wave)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(seed)
    x0 = t.template + 0.002 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    v0 = 0.05 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    p = PhysicsParams.default(N, t.num_vertices)
    p.a_vert = 0.5 * torch.randn(N - 1, t.num_vertices, 3, generator=g, dtype=torch.float64)
    W = torch.randn(N, t.num_vertices, 3, generator=g, dtype=torch.float64)
    return t, x0, v0, p, W


def _gradcheck(mode, pinned=None, pinned_positions=None, x0_eps=1e-6, anchored=False, drag=False):
    t, x0, v0, p, W = _setup()
    if drag:  # c = 30 kg/m^3 (strong, so that the term matters at these speeds)
        p.log10_drag = torch.tensor(1.5, dtype=torch.float64)
    kw = dict(num_frames=N, hessian=mode, tol=1e-13, pinned=pinned, pinned_positions=pinned_positions)
    if anchored:
        # stiff and weak anchors (w h^2 from 0 to 10), pulling towards points off the start state
        g = torch.Generator().manual_seed(3)
        p.anchor = 4e5 * torch.rand(t.num_vertices, generator=g, dtype=torch.float64) ** 2
        kw["anchor_positions"] = t.template + 0.01 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)

    def loss():
        return (rollout(t, x0, v0, p, **kw) * W).sum()

    leaves = dict(x0=x0, v0=v0, log10_Y=p.log10_Y, log10_B=p.log10_B, log10_S=p.log10_S,
                  damping=p.damping, a_const=p.a_const, a_vert=p.a_vert)
    if anchored:
        leaves["anchor"] = p.anchor
    if drag:
        leaves["log10_drag"] = p.log10_drag
    for val in leaves.values():
        val.requires_grad_(True)
    loss().backward()
    g = torch.Generator().manual_seed(7)
    for name, val in leaves.items():
        assert val.grad is not None, name
        d = torch.randn(val.shape, generator=g, dtype=val.dtype)
        if pinned is not None and name in ("x0", "v0"):
            d[pinned] = 0.0  # pinned targets are constants (documented)
        eps = x0_eps if name == "x0" else (1e-6 * float(val.detach().abs().max()) if name == "anchor" else 1e-6)
        with torch.no_grad():
            val.add_(eps * d)
            lp = loss()
            val.sub_(2 * eps * d)
            lm = loss()
            val.add_(eps * d)
        fd = ((lp - lm) / (2 * eps)).item()
        an = (val.grad * d).sum().item()
        rel = 2e-4 if name != "x0" else 1e-3  # x0 needs a tiny eps (kinks/nonlinearity): noisier FD
        assert an == pytest.approx(fd, rel=rel, abs=1e-9), f"{name}: adjoint {an} vs central FD {fd}"


def test_rollout_gradients_vs_finite_differences_projected():
    _gradcheck("projected")


def test_rollout_gradients_vs_finite_differences_exact_hessian():
    # the exact-Hessian dynamics of this (compressed, noisy) cloth are strongly nonlinear in x0
    _gradcheck("exact", x0_eps=1e-8)


def test_rollout_gradients_vs_finite_differences_pinned():
    # projected Hessian: springs crossing their rest length are kinks of the dynamics, so x0 needs a
    # small step (the exact-Hessian dynamics of this pinned, compressed cloth blow up: not tested here)
    _gradcheck("projected", pinned=[0, 1, 2, 3, 4], x0_eps=1e-8)


def test_rollout_gradients_vs_finite_differences_anchored():
    _gradcheck("projected", anchored=True, x0_eps=1e-8)


def test_rollout_gradients_vs_finite_differences_anchored_and_pinned():
    _gradcheck("projected", pinned=[0, 1, 2], anchored=True, x0_eps=1e-8)


def test_rollout_gradients_vs_finite_differences_air_drag():
    _gradcheck("projected", drag=True, x0_eps=1e-8)


def test_rollout_gradients_vs_finite_differences_air_drag_pinned():
    _gradcheck("projected", pinned=[0, 1, 2, 3, 4], drag=True, x0_eps=1e-8)


def test_stiff_anchors_hold_vertices_like_pins_and_zero_anchors_change_nothing():
    v, q = grid_mesh(6, plane="xy")
    t = ClothTopology.from_quads(v, q)
    top = np.arange(7)  # row 0: the top edge
    p = PhysicsParams.default()
    free = rollout(t, t.template, None, p, num_frames=8)
    p.anchor = torch.zeros(t.num_vertices, dtype=torch.float64)
    assert torch.equal(rollout(t, t.template, None, p, num_frames=8), free)
    pinned = rollout(t, t.template, None, PhysicsParams.default(), num_frames=8, pinned=top)
    p.anchor[top] = 1e9  # w h^2 = 2.5e4: the top edge is held to within a micrometre
    held = rollout(t, t.template, None, p, num_frames=8)
    assert (held[:, top] - t.template[top]).abs().max() < 1e-5
    assert (held - pinned).abs().max() < 1e-4
    assert (free[-1, top] - t.template[top]).abs().max() > 0.01  # without anchors it falls


def test_one_substep_solves_the_linearised_backward_eulergrid_system():
    t, x0, v0, p, _ = _setup()
    h = 0.02
    pos = rollout(t, x0, v0, p, num_frames=2, substeps=1, tol=1e-13, hessian="exact")
    ev = ElementEval(t, x0, 200.0, 1e-3, 1e-4, "exact")
    n = 3 * t.num_vertices
    K = sp.csr_matrix((ev.hessian_values().numpy(), t.csr_indices, t.csr_indptr), shape=(n, n)).toarray()
    M = np.repeat(t.mass.numpy(), 3)
    a = (p.a_const + p.a_vert[0]).numpy().reshape(-1)
    b = M * (0.9 * v0.numpy().reshape(-1)) + h * (-ev.grad().T.reshape(-1).numpy() + M * a)
    v1 = np.linalg.solve(np.diag(M) + h * h * K, b)
    assert np.allclose(pos[1].reshape(-1).numpy(), x0.reshape(-1).numpy() + h * v1, rtol=0, atol=1e-12)


def test_indefinite_system_compressed_cloth():
    """3% compression makes M + h^2 K indefinite with the exact Hessian: the exact mode must still solve
    it (LU fallback), and the projected mode must stay SPD (PCG, no fallback)."""
    v, q = grid_mesh(4, wave=0.0)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(1)
    x0 = 0.97 * t.template + 1e-4 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    p = PhysicsParams.default()
    M = np.repeat(t.mass.numpy(), 3)
    n = 3 * t.num_vertices
    K = sp.csr_matrix(
        (ElementEval(t, x0, 200.0, 1e-3, 1e-4, "exact").hessian_values().numpy(), t.csr_indices, t.csr_indptr),
        shape=(n, n),
    ).toarray()
    assert np.linalg.eigvalsh(np.diag(M) + 0.005**2 * K).min() < 0  # really indefinite
    out = {}
    for mode in ("exact", "projected"):
        st = {}
        pos = rollout(t, x0, None, p, num_frames=4, hessian=mode, tol=1e-12, stats=st)
        assert torch.isfinite(pos).all()
        # the compressed sheet expands back towards its rest size
        span0 = (x0[:, 0].max() - x0[:, 0].min()).item()
        span = (pos[-1][:, 0].max() - pos[-1][:, 0].min()).item()
        assert span > span0
        out[mode] = st
    assert out["projected"]["fallbacks"] == 0
    # exact mode, first substep: check the residual of the indefinite system explicitly
    pos = rollout(t, x0, None, p, num_frames=2, substeps=1, hessian="exact", tol=1e-13)
    h = 0.02
    Kh = K
    b = h * (-ElementEval(t, x0, 200.0, 1e-3, 1e-4, "exact").grad().T.reshape(-1).numpy() + M * np.tile(p.a_const.numpy(), t.num_vertices))
    v1 = (pos[1] - x0).reshape(-1).numpy() / h
    A = np.diag(M) + h * h * Kh
    assert np.linalg.norm(A @ v1 - b) <= 1e-9 * np.linalg.norm(b)


def test_pinned_cloth_settles_under_gravity():
    n = 6
    v, q = grid_mesh(n, size=0.3, plane="xy")  # hanging sheet, row 0 on top
    t = ClothTopology.from_quads(v, q)
    top = list(range(n + 1))
    frames = 150  # 3 s
    pos = rollout(t, t.template, None, PhysicsParams.default(), num_frames=frames, pinned=top)
    assert torch.isfinite(pos).all()
    assert torch.equal(pos[:, top], t.template[top].expand(frames, -1, -1))  # exactly pinned
    step = (pos[-1] - pos[-2]).abs().max().item()
    assert step < 1e-6  # at rest (damping 0.9 per substep)
    # it hangs: nothing above the pinned edge, bottom row sagged a little (springs stretch, not explode)
    assert pos[-1][:, 1].max().item() <= 1e-9
    drop = (t.template[-1, 1] - pos[-1][-1, 1]).item()
    assert 0 < drop < 0.05
    e = t.edges
    strain = ((pos[-1][e[:, 1]] - pos[-1][e[:, 0]]).norm(dim=1) / t.rest_len - 1).abs().max().item()
    assert strain < 0.2
    # static equilibrium: internal forces balance gravity at the free vertices
    ev = ElementEval(t, pos[-1], 200.0, 1e-3, 1e-4, "exact")
    f = -ev.grad().T + t.mass[:, None] * torch.tensor([0.0, -9.81, 0.0], dtype=torch.float64)
    free = torch.ones(t.num_vertices, dtype=torch.bool)
    free[top] = False
    assert f[free].abs().max().item() < 1e-3 * (t.mass.max().item() * 9.81)


def test_pinned_vertices_follow_prescribed_positions_exactly():
    t, x0, v0, p, _ = _setup()
    P = [0, 5, 24]
    tt = torch.arange(N, dtype=torch.float64)[:, None, None]
    targets = x0[P][None] + tt * torch.tensor([0.0, 0.003, 0.001], dtype=torch.float64)
    pos = rollout(t, x0, v0, p, num_frames=N, pinned=P, pinned_positions=targets)
    assert torch.equal(pos[:, P], targets)
    assert torch.isfinite(pos).all()


def test_nan_raises_simulation_error_naming_frame_and_substep(monkeypatch):
    t, x0, v0, p, _ = _setup()
    bad = p.a_vert.clone()
    bad[3, 7, 1] = float("nan")
    p.a_vert = bad
    with pytest.raises(SimulationError, match=r"frame 3, substep 0"):
        rollout(t, x0, v0, p, num_frames=N)
    p.a_vert = None
    # a NaN that appears inside the simulation (third substep of frame 1)
    import saft.physics.simulation as R

    calls = {"n": 0}
    orig = R.ElementEval.grad

    def poisoned(self):
        calls["n"] += 1
        g = orig(self)
        return g * float("nan") if calls["n"] == 4 + 3 else g

    monkeypatch.setattr(R.ElementEval, "grad", poisoned)
    monkeypatch.setenv("SAFT_PHYSICS_KERNELS", "torch")  # ElementEval is what the torch kernels call
    with pytest.raises(SimulationError, match=r"frame 1, substep 2"):
        rollout(t, x0, v0, p, num_frames=N)
    monkeypatch.undo()
    with pytest.raises(SimulationError, match=r"frame 0, substep 0"):
        rollout(t, x0 * float("inf"), v0, p, num_frames=N)


def test_torch_cg_solver_matches_lu_solver():
    """The device-agnostic torch path (used on CUDA) gives the same rollout and gradients on CPU."""
    t, x0, v0, p, W = _setup()
    res = {}
    for solver in ("lu", "cg"):
        pp = PhysicsParams(*(x.detach().clone().requires_grad_(True) for x in p.tensors()))
        pos = rollout(t, x0, v0, pp, num_frames=N, solver=solver, tol=1e-12)
        (pos * W).sum().backward()
        res[solver] = (pos.detach(), [x.grad for x in pp.tensors()])
    assert torch.allclose(res["lu"][0], res["cg"][0], atol=1e-10)
    for a, b in zip(res["lu"][1], res["cg"][1]):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-8 * b.abs().max().item())


@pytest.mark.parametrize("mode", ["projected", "exact"])
def test_cholmod_solver_matches_lu_solver(mode):
    """The opt-in CHOLMOD-preconditioned path gives the same rollout and gradients as the SuperLU one
    (tol 1e-12: positions to 1e-10, gradients to rtol 1e-6)."""
    t, x0, v0, p, W = _setup()
    if not S.HAVE_CHOLMOD:
        with pytest.raises(ValueError, match="scikit-sparse"):
            rollout(t, x0, v0, p, num_frames=N, solver="cholmod")
        pytest.skip("scikit-sparse (CHOLMOD) not installed")
    res = {}
    for solver in ("lu", "cholmod"):
        pp = PhysicsParams(*(x.detach().clone().requires_grad_(True) for x in p.tensors()))
        pos = rollout(t, x0, v0, pp, num_frames=N, solver=solver, tol=1e-12, hessian=mode)
        (pos * W).sum().backward()
        res[solver] = (pos.detach(), [x.grad for x in pp.tensors()])
    assert torch.allclose(res["lu"][0], res["cholmod"][0], atol=1e-10)
    for a, b in zip(res["lu"][1], res["cholmod"][1]):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-8 * b.abs().max().item())


def _rollout_and_grads(t, x0, v0, p, W, **kw):
    pp = PhysicsParams(*(x.detach().clone().requires_grad_(True) for x in p.tensors()))
    pos = rollout(t, x0, v0, pp, num_frames=N, **kw)
    (pos * W).sum().backward()
    return [pos.detach()] + [x.grad for x in pp.tensors()]


def test_default_solver_is_deterministic_and_ignores_optional_packages(monkeypatch):
    """The default CPU path gives the same bits on every run, with 1 or 2 torch threads, and whether or not
    CHOLMOD is importable ("auto" never picks a different numerical method from what is installed)."""
    t, x0, v0, p, W = _setup(n=6)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        ref = _rollout_and_grads(t, x0, v0, p, W)
        torch.set_num_threads(2)
        runs = [_rollout_and_grads(t, x0, v0, p, W), _rollout_and_grads(t, x0, v0, p, W, solver="lu")]
        assert torch.get_num_threads() == 2  # the rollout runs on one thread and restores the caller's count
        monkeypatch.setattr(S, "HAVE_CHOLMOD", True)  # as if scikit-sparse were installed
        runs.append(_rollout_and_grads(t, x0, v0, p, W, solver="auto"))
    finally:
        torch.set_num_threads(threads)
    for run in runs:
        for a, b in zip(ref, run):
            assert torch.equal(a, b)




@pytest.mark.parametrize("drop_tol", [1e-4, 0.0])
def test_reused_factor_solver_matches_direct_solve(drop_tol):
    """CG preconditioned by the (incomplete, default) or complete LU of a drifted matrix reaches the direct
    solution; the incomplete factor has fewer entries than the complete one."""
    t, A0, _, _ = grid_system("projected")
    _, A, b, Am = grid_system("projected", drift=2e-4)
    s = ReusedLUSolver(t.csr_indptr, t.csr_indices, tol=1e-12, drop_tol=drop_tol)
    s.factorize(A0)
    assert s.incomplete == (drop_tol > 0)
    x = s.solve(A, b)
    ref = spla.spsolve(Am.tocsc(), b)
    assert np.abs(x - ref).max() <= 1e-9 * np.abs(ref).max()
    assert s.stats.fallbacks == 0 and 0 < s.stats.iterations <= s.max_iter
    if drop_tol:
        full = ReusedLUSolver(t.csr_indptr, t.csr_indices, drop_tol=0.0)
        full.factorize(A0)
        assert s.lu.nnz < full.lu.nnz


def test_reused_factor_solver_indefinite_matrix_falls_back_to_pivoted_lu():
    """The exact Hessian under compression makes A indefinite: CG breaks down, the solver falls back to a
    complete factorisation and a direct solve, still to the requested tolerance."""
    t, A, b, Am = grid_system("exact", compress=0.97)
    assert np.linalg.eigvalsh(Am.toarray()).min() < 0
    s = ReusedLUSolver(t.csr_indptr, t.csr_indices, tol=1e-10)
    x = s.solve(A, b)
    assert np.linalg.norm(Am @ x - b) <= 1e-10 * np.linalg.norm(b)
    ref = spla.spsolve(Am.tocsc(), b)
    assert np.abs(x - ref).max() <= 1e-6 * np.abs(ref).max()
    assert not s.incomplete


def test_float32_inputs_and_defaults():
    t, x0, _, _, _ = _setup()
    pos = rollout(t, x0.float(), num_frames=3)
    assert pos.shape == (3, t.num_vertices, 3) and pos.dtype == torch.float64
    assert torch.equal(pos[0], x0.float().double())
    assert (pos[-1][:, 1] < x0[:, 1]).all()  # falls under gravity


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs an NVIDIA GPU")
def test_cuda_matches_cpu():
    t, x0, v0, p, W = _setup()
    tc = t.to("cuda")
    out = {}
    for dev, topo in (("cpu", t), ("cuda", tc)):
        pp = PhysicsParams(*(x.detach().clone().to(dev).requires_grad_(True) for x in p.tensors()))
        pos = rollout(topo, x0.to(dev), v0.to(dev), pp, num_frames=N, tol=1e-12)
        (pos * W.to(dev)).sum().backward()
        out[dev] = (pos.detach().cpu(), [x.grad.cpu() for x in pp.tensors()])
    assert torch.allclose(out["cpu"][0], out["cuda"][0], atol=1e-9)
    for a, b in zip(out["cpu"][1], out["cuda"][1]):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-7 * a.abs().max().item())


def test_kernel_compile_failure_falls_back_to_eager(monkeypatch):
    """compile=True with a broken compiler warns once and gives the eager result; backward solver
    counters are reported as bwd_* and the adjoint reuses the forward's kept factors."""
    import saft.physics.kernels as K

    monkeypatch.setenv("SAFT_PHYSICS_KERNELS", "torch")  # compile=False would otherwise pick numba
    t, x0, v0, p, W = _setup()
    for val in p.tensors():
        val.requires_grad_(True)
    st = {}
    ref = rollout(t, x0, v0, p, num_frames=N, tol=1e-12, stats=st, compile=False)
    (ref * W).sum().backward()
    g_ref = [x.grad.clone() for x in p.tensors()]
    assert st["bwd_solves"] == st["solves"] and st["bwd_factorizations"] == 0

    def broken(*a, **k):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(K.torch, "compile", broken)
    monkeypatch.setattr(K, "_compiled", {})
    monkeypatch.setattr(K, "_compile_failed", False)
    for val in p.tensors():
        val.grad = None
    with pytest.warns(RuntimeWarning, match="running them eagerly"):
        pos = rollout(t, x0, v0, p, num_frames=N, tol=1e-12, compile=True)
    (pos * W).sum().backward()
    assert torch.equal(pos.detach(), ref.detach())
    for a, b in zip(g_ref, [x.grad for x in p.tensors()]):
        assert torch.equal(a, b)


def test_compile_is_on_by_default_on_cuda_only(monkeypatch):
    """torch.compile of the element kernels and the dense CG: on by default on CUDA (measured faster there),
    off on the CPU (numba); SAFT_PHYSICS_COMPILE and the argument override both ways."""
    from saft.physics.kernels import ENV_COMPILE, compile_requested

    monkeypatch.delenv(ENV_COMPILE, raising=False)
    assert compile_requested(None, torch.device("cuda")) and not compile_requested(None, torch.device("cpu"))
    assert not compile_requested(None)
    monkeypatch.setenv(ENV_COMPILE, "0")
    assert not compile_requested(None, torch.device("cuda"))
    monkeypatch.setenv(ENV_COMPILE, "1")
    assert compile_requested(None, torch.device("cpu"))
    assert not compile_requested(False, torch.device("cuda"))


def test_on_frame_sees_every_frame_as_it_is_done_and_changes_nothing():
    """rollout's on_frame: called once per frame, in order, frame 0 included, with that frame's positions as
    returned; the rollout with the hook equals the one without, bit for bit."""
    t, x0, v0, p, _ = _setup()
    seen = []
    with_hook = rollout(t, x0, v0, p, num_frames=N, on_frame=lambda k, x: seen.append((k, x.clone())))
    plain = rollout(t, x0, v0, p, num_frames=N)
    assert [k for k, _ in seen] == list(range(N))
    assert torch.equal(with_hook, plain)
    for k, x in seen:
        assert torch.equal(x, plain[k])
