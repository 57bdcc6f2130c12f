import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import cube_mesh, grid_mesh  # noqa: E402

from saft.physics import ClothTopology, ElementEval, deformation_energy  # noqa: E402

LY, LB, LS = math.log10(200.0), -3.0, -4.0
Y, B, S = 200.0, 1e-3, 1e-4


def _topo(mesh="grid"):
    v, q = grid_mesh(3, wave=0.01) if mesh == "grid" else cube_mesh()
    return ClothTopology.from_quads(v, q)


def _perturbed(t, scale=0.003, seed=0):
    g = torch.Generator().manual_seed(seed)
    return t.template + scale * torch.randn(t.template.shape, generator=g, dtype=torch.float64)


def _dense(t, data):
    n = 3 * t.num_vertices
    return sp.csr_matrix((data.numpy(), t.csr_indices, t.csr_indptr), shape=(n, n)).toarray()


def _energy_flat(t):
    return lambda z: deformation_energy(z.view(-1, 3), t, LY, LB, LS)


def test_energy_zero_at_rest_and_positive_elsewhere():
    t = _topo()
    assert deformation_energy(t.template, t, LY, LB, LS).item() == pytest.approx(0.0, abs=1e-20)
    assert deformation_energy(_perturbed(t), t, LY, LB, LS).item() > 0


def test_energy_terms_by_hand():
    # one quad, stretch one edge by 1 mm: only E_Y changes at first order
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float) * 0.1
    t = ClothTopology.from_quads(v, np.array([[0, 1, 2, 3]]))
    x = t.template.clone()
    x[1, 0] += 0.001
    x[2, 0] += 0.001
    EY, EB, ES = deformation_energy(x, t, LY, LB, LS, per_term=True)
    assert EY.item() == pytest.approx(2 * 0.5 * Y * 0.001**2, rel=1e-9)  # two edges stretched by 1 mm
    assert EB.item() == 0.0  # a single quad has no straight pairs
    assert ES.item() == pytest.approx(0.0, abs=1e-30)


@pytest.mark.parametrize("mesh", ["grid", "cube"])
def test_batched_energy_matches_per_frame(mesh):
    t = _topo(mesh)
    xs = torch.stack([_perturbed(t, seed=s) for s in range(3)])
    Eb = deformation_energy(xs, t, LY, LB, LS)
    assert Eb.shape == (3,)
    for i in range(3):
        assert Eb[i].item() == pytest.approx(deformation_energy(xs[i], t, LY, LB, LS).item(), rel=1e-12)


@pytest.mark.parametrize("mode", ["exact", "projected"])
@pytest.mark.parametrize("mesh", ["grid", "cube"])
def test_closed_form_gradient_vs_finite_differences(mode, mesh):
    t = _topo(mesh)
    x = _perturbed(t)
    ev = ElementEval(t, x, Y, B, S, mode)
    g = ev.grad().T.reshape(-1)
    f = _energy_flat(t)
    xf = x.reshape(-1)
    eps = 1e-7
    fd = torch.stack([(f(xf + eps * e) - f(xf - eps * e)) / (2 * eps) for e in torch.eye(xf.numel(), dtype=xf.dtype)])
    assert torch.allclose(g, fd, rtol=1e-5, atol=1e-7 * fd.abs().max().item())


@pytest.mark.parametrize("mesh", ["grid", "cube"])
def test_exact_hessian_vs_finite_differences_of_gradient(mesh):
    t = _topo(mesh)
    x = _perturbed(t)
    H = _dense(t, ElementEval(t, x, Y, B, S, "exact").hessian_values())
    n = 3 * t.num_vertices
    eps = 1e-7
    fd = np.zeros((n, n))
    for j in range(n):
        e = torch.zeros(n, dtype=torch.float64)
        e[j] = eps
        gp = ElementEval(t, x + e.view(-1, 3), Y, B, S, "exact").grad().T.reshape(-1)
        gm = ElementEval(t, x - e.view(-1, 3), Y, B, S, "exact").grad().T.reshape(-1)
        fd[:, j] = ((gp - gm) / (2 * eps)).numpy()
    assert np.abs(H - fd).max() <= 1e-5 * np.abs(fd).max()
    assert np.abs(H - H.T).max() <= 1e-12 * np.abs(H).max()
    # the closed-form exact HVP agrees with the assembled matrix
    lam = torch.randn(t.num_vertices, 3, dtype=torch.float64)
    ev = ElementEval(t, x, Y, B, S, "projected")
    hv = ev.scatter(ev.exact_hvp_parts(lam.T)).T.reshape(-1).numpy()
    assert np.allclose(hv, H @ lam.reshape(-1).numpy(), rtol=1e-9, atol=1e-9 * np.abs(hv).max())


def test_projected_hessian_is_psd_and_exact_is_not_under_compression():
    v, q = grid_mesh(4, wave=0.0)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(1)
    x = 0.97 * t.template + 1e-4 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)  # 3% compression
    Hx = _dense(t, ElementEval(t, x, Y, B, S, "exact").hessian_values())
    Hp = _dense(t, ElementEval(t, x, Y, B, S, "projected").hessian_values())
    assert np.linalg.eigvalsh(Hx).min() < -1e-3 * np.abs(Hx).max()
    assert np.linalg.eigvalsh(Hp).min() > -1e-10 * np.abs(Hp).max()
    # with h = 5 ms the exact system matrix itself is indefinite, the projected one SPD
    M = np.repeat(t.mass.numpy(), 3)
    h2 = 0.005**2
    assert np.linalg.eigvalsh(np.diag(M) + h2 * Hx).min() < 0
    assert np.linalg.eigvalsh(np.diag(M) + h2 * Hp).min() > 0


def _adjoint_case(seed):
    """A perturbed grid and random (lam, w) fields (V, 3) for the adjoint-kernel tests."""
    t = _topo()
    g = torch.Generator().manual_seed(seed)
    lam = torch.randn(t.num_vertices, 3, generator=g, dtype=torch.float64)
    w = torch.randn(t.num_vertices, 3, generator=g, dtype=torch.float64)
    return t, _perturbed(t), lam, w


@pytest.mark.parametrize("mode", ["exact", "projected"])
def test_third_derivative_contraction_vs_autograd(mode):
    t, x, lam, w = _adjoint_case(seed=3)
    n = 3 * t.num_vertices
    rows = torch.as_tensor(np.repeat(np.arange(n), np.diff(t.csr_indptr)))
    cols = torch.as_tensor(t.csr_indices)
    xr = x.clone().requires_grad_(True)
    K = ElementEval(t, xr, Y, B, S, mode).hessian_values()
    s = (lam.reshape(-1)[rows] * K * w.reshape(-1)[cols]).sum()
    (ref,) = torch.autograd.grad(s, xr)
    ev = ElementEval(t, x, Y, B, S, mode)
    adj = ev.adjoint_terms(lam.T, w.T)
    T = ev.scatter(adj["third_parts"]).T
    assert torch.allclose(T, ref, rtol=1e-9, atol=1e-9 * ref.abs().max().item())
    lKw = adj["spring_lKw"].sum() + adj["hinge_lKw"].sum()
    assert lKw.item() == pytest.approx(s.item(), rel=1e-10)


def test_energy_gradient_wrt_log_stiffness():
    t = _topo()
    x = _perturbed(t)
    p = torch.tensor([LY, LB, LS], dtype=torch.float64, requires_grad=True)
    E = deformation_energy(x, t, p[0], p[1], p[2])
    (g,) = torch.autograd.grad(E, p)
    terms = deformation_energy(x, t, LY, LB, LS, per_term=True)
    # E_k is linear in k = 10^p: dE/dp = ln(10) E_k
    assert torch.allclose(g, math.log(10) * torch.stack(terms), rtol=1e-12)


@pytest.mark.parametrize("mesh", ["grid", "cube"])
def test_upper_triangle_assembly_matches_full_blocks(mesh):
    """The projected K assembled from each element's unique entries (upper storage, mirrored) equals the
    reference assembly of every full element block, and A = M + h^2 K adds the masses on the diagonal."""
    t = _topo(mesh)
    x = _perturbed(t, scale=0.01)
    ev = ElementEval(t, x, Y, B, S, "projected")
    ref = ev._hessian_values_blocks()
    K = ev.hessian_values()
    assert torch.allclose(K, ref, rtol=1e-13, atol=1e-14 * ref.abs().max().item())
    Kd = _dense(t, K)
    assert np.abs(Kd - Kd.T).max() == 0.0
    hh = 0.005**2
    md = t.mass.repeat_interleave(3)
    A = ev.system_values(hh, md)
    Aref = (hh * ref).index_add(0, t.diag_idx, md)
    assert torch.allclose(A, Aref, rtol=1e-13, atol=1e-14 * Aref.abs().max().item())


@pytest.mark.parametrize("mode", ["exact", "projected"])
def test_fused_adjoint_increment_matches_separate_terms(mode):
    t, x, lam, w = _adjoint_case(seed=5)
    h = 0.005
    ev = ElementEval(t, x, Y, B, S, mode)
    parts, gY, hc = ev.adjoint_increment(lam.T, w.T, h)
    adj = ev.adjoint_terms(lam.T, w.T)
    ref = -h * ev.exact_hvp_parts(lam.T) - h * h * adj["third_parts"]
    assert torch.allclose(parts, ref, rtol=1e-12, atol=1e-13 * ref.abs().max().item())
    assert gY.item() == pytest.approx((-h * adj["spring_lg"] - h * h * adj["spring_lKw"]).sum().item(), rel=1e-12)
    assert torch.allclose(hc, -h * adj["hinge_lg"] - h * h * adj["hinge_lKw"], rtol=1e-12, atol=0)
