import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from physics_helpers import grid_mesh  # noqa: E402

from saft.physics import ClothTopology, PhysicsParams, rollout  # noqa: E402
from saft.physics.drag import drag_force, drag_vjp  # noqa: E402


def _flat(n=4):
    v, q = grid_mesh(n, wave=0.0, plane="xy")
    return ClothTopology.from_quads(v, q)


def test_a_flat_sheet_moving_along_its_normal_feels_c_area_u_squared():
    t = _flat()
    x = t.template
    tri = t.triangles
    areas = 0.5 * torch.linalg.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]).norm(dim=1)
    area = float(areas.sum())
    c = torch.tensor(0.6, dtype=torch.float64)
    v = torch.zeros_like(x)
    v[:, 2] = 2.0  # along the normal
    f = drag_force(x, v, tri, c)
    assert f[:, :2].abs().max() < 1e-12
    assert float(f[:, 2].sum()) == pytest.approx(-0.6 * area * 4.0, rel=1e-12)
    v[:, 2] = -2.0  # opposes the motion either way
    assert float(drag_force(x, v, tri, c)[:, 2].sum()) == pytest.approx(0.6 * area * 4.0, rel=1e-12)
    v = torch.zeros_like(x)
    v[:, 0] = 3.0  # sliding in its own plane: no pressure drag
    assert drag_force(x, v, tri, c).abs().max() < 1e-12


def test_drag_vjp_matches_finite_differences():
    v, q = grid_mesh(3, wave=0.05)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(0)
    x = t.template + 0.01 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    vel = torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    lam = torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    c = torch.tensor(0.8, dtype=torch.float64)
    gx, gv, gc = drag_vjp(x, vel, t.triangles, c, lam)

    def f(xx, vv, cc):
        return float((drag_force(xx, vv, t.triangles, cc) * lam).sum())

    eps = 1e-6
    for grad, which in ((gx, 0), (gv, 1)):
        d = torch.randn(x.shape, generator=g, dtype=torch.float64)
        args_p = [x, vel, c]
        args_m = [x, vel, c]
        args_p[which] = args_p[which] + eps * d
        args_m[which] = args_m[which] - eps * d
        fd = (f(*args_p) - f(*args_m)) / (2 * eps)
        assert float((grad * d).sum()) == pytest.approx(fd, rel=1e-6, abs=1e-10)
    fd = (f(x, vel, c + eps) - f(x, vel, c - eps)) / (2 * eps)
    assert float(gc) == pytest.approx(fd, rel=1e-6)


def test_drag_slows_a_falling_sheet_and_is_off_by_default():
    t = _flat(5)
    p = PhysicsParams.default()
    p.damping = torch.tensor(1.0, dtype=torch.float64)
    p.a_const = torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)  # falls along its normal
    free = rollout(t, t.template, None, p, num_frames=20, frame_dt=1 / 30)
    p.log10_drag = torch.tensor(0.0, dtype=torch.float64)  # c = 1 kg/m^3, density 0.1 kg/m^2
    slowed = rollout(t, t.template, None, p, num_frames=20, frame_dt=1 / 30)
    fall_free = -float(free[-1, :, 2].mean())
    fall_drag = -float(slowed[-1, :, 2].mean())
    assert fall_free == pytest.approx(0.5 * 9.81 * (19 / 30) ** 2, rel=0.05)
    # terminal speed sqrt(rho_s g / c) ~ 0.99 m/s: over 0.63 s the sheet falls well under a metre
    assert 0.3 < fall_drag < 0.7


def test_drag_agrees_between_numba_and_torch_kernels():
    v, q = grid_mesh(4, wave=0.03)
    t = ClothTopology.from_quads(v, q)
    p = PhysicsParams.default()
    p.log10_drag = torch.tensor(0.5, dtype=torch.float64)
    v0 = torch.zeros_like(t.template)
    v0[:, 1] = 1.0
    a = rollout(t, t.template, v0, p, num_frames=6, kernels="numba", tol=1e-12)
    b = rollout(t, t.template, v0, p, num_frames=6, kernels="torch", tol=1e-12)
    assert (a - b).abs().max() < 1e-9


def test_drag_vjp_equals_autograd_of_the_force():
    v, q = grid_mesh(4, wave=0.05)
    t = ClothTopology.from_quads(v, q)
    g = torch.Generator().manual_seed(2)
    x = (t.template + 0.01 * torch.randn(t.template.shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    vel = torch.randn(t.template.shape, generator=g, dtype=torch.float64).requires_grad_(True)
    c = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    lam = torch.randn(t.template.shape, generator=g, dtype=torch.float64)
    ref = torch.autograd.grad((drag_force(x, vel, t.triangles, c) * lam).sum(), (x, vel, c))
    got = drag_vjp(x.detach(), vel.detach(), t.triangles, c.detach(), lam)
    for r, o in zip(ref, got):
        assert torch.allclose(r, o, rtol=1e-10, atol=1e-14)


def test_the_numba_loops_give_the_torch_ops_bits():
    """On CPU float64 drag_force / drag_vjp run drag_numba's loops: the same bits as the torch formulation
    (random cloth-like and degenerate triangles: a collapsed one gives the same nan), where torch's cross
    product rounds as ATen's kernel does on this project's machines (fused multiply-add; checked first);
    elsewhere equal to rounding."""
    from saft.physics import drag_numba
    from saft.physics.drag import drag_force_torch, drag_vjp_torch

    g = torch.Generator().manual_seed(0)
    drag_numba.load()
    a, b = torch.randn(2, 64, 3, generator=g, dtype=torch.float64)
    fused = all(torch.equal(torch.linalg.cross(a[i:i + 1], b[i:i + 1])[0],
                            torch.tensor(drag_numba._cross(*a[i].tolist(), *b[i].tolist()), dtype=torch.float64))
                for i in range(64))
    V, T = 200, 400
    for trial in range(5):
        x, v, lam = (torch.randn(V, 3, generator=g, dtype=torch.float64) for _ in range(3))
        tri = torch.randint(0, V, (T, 3), generator=g)
        tri[0, 1] = tri[0, 0]   # a collapsed triangle
        c = torch.tensor(0.3 + 0.4 * trial, dtype=torch.float64)

        def same(a, b):
            close = (a == b) if fused else torch.isclose(a, b, rtol=1e-12, atol=1e-15)
            return bool((close | (a.isnan() & b.isnan())).all())

        assert same(drag_force(x, v, tri, c), drag_force_torch(x, v, tri, c))
        for got, ref in zip(drag_vjp(x, v, tri, c, lam), drag_vjp_torch(x, v, tri, c, lam)):
            assert same(got, ref)
