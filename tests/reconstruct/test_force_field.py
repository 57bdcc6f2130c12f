"""The per-frame affine acceleration field (saft.reconstruct.force_field) and how the shape phase uses it."""

import numpy as np
import pytest
import torch

from saft.reconstruct.config import PhysicsConfig, ShapeConfig
from saft.reconstruct.force_field import affine_basis, field_accelerations, total_accelerations


def test_affine_basis_is_the_centred_scaled_template():
    template = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 1.0, 0.0]], dtype=torch.float64)
    b = affine_basis(template)
    assert b.shape == (4, 4)
    assert torch.equal(b[:, 0], torch.ones(4, dtype=torch.float64))
    assert torch.allclose(b[:, 1], torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))   # x: half-extent 1
    assert torch.allclose(b[:, 2], torch.tensor([-0.5, -0.5, 0.5, 0.5], dtype=torch.float64))   # y: same scale
    assert torch.equal(b[:, 3], torch.zeros(4, dtype=torch.float64))                          # flat in z


def test_field_accelerations_match_the_affine_formula():
    gen = torch.Generator().manual_seed(0)
    template = torch.randn(7, 3, generator=gen, dtype=torch.float64)
    coeffs = torch.randn(3, 4, 3, generator=gen, dtype=torch.float64)
    basis = affine_basis(template)
    a = field_accelerations(coeffs, basis)
    assert a.shape == (3, 7, 3)
    k, v = 2, 5
    expected = coeffs[k, 0] + basis[v, 1] * coeffs[k, 1] + basis[v, 2] * coeffs[k, 2] + basis[v, 3] * coeffs[k, 3]
    assert torch.allclose(a[k, v], expected)
    d_f = torch.randn(3, 7, 3, generator=gen, dtype=torch.float64)
    assert torch.equal(total_accelerations(d_f, coeffs, basis), d_f + a)
    assert total_accelerations(d_f, None, basis) is d_f


def _sim_and_state(cfg, frames=6, pinned=None):
    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.synthetic import grid_template

    mesh = grid_template(5, 0.3)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 0.02, pinned)
    state = new_shape_state(frames, len(template), np.zeros(3), PhysicsConfig(), cfg, "cpu")
    return sim, state


def test_the_field_is_on_by_default_off_at_rate_zero_and_adds_to_the_vertex_accelerations():
    _, off = _sim_and_state(ShapeConfig(lr_field_accel=0.0))
    assert off.params.field_accel is None and "field_accel" not in off.params.tensors()
    _, default = _sim_and_state(ShapeConfig())
    assert default.params.field_accel is not None
    sim, on = _sim_and_state(ShapeConfig(lr_field_accel=1.0))
    p = on.params
    assert p.field_accel.shape == (5, 4, 3) and "field_accel" in p.tensors()
    with torch.no_grad():
        p.field_accel[1, 0] = torch.tensor([0.0, 3.0, 0.0], dtype=p.field_accel.dtype)   # uniform lift in frame 1
    a = p.accelerations(sim.field_basis, 0, 5)
    assert torch.allclose(a[1, :, 1], torch.full((a.shape[1],), 3.0, dtype=a.dtype))
    assert torch.equal(a[0], p.vertex_accel[0])


def test_a_uniform_field_moves_the_cloth_as_the_same_per_vertex_accelerations_do():
    sim, state = _sim_and_state(ShapeConfig(lr_field_accel=1.0))
    p = state.params
    with torch.no_grad():
        p.field_accel[:, 0] = torch.tensor([0.5, 2.0, -1.0], dtype=p.field_accel.dtype)
        via_field = sim.simulate(p, 6)
        p.field_accel.zero_()
        p.vertex_accel[:] = torch.tensor([0.5, 2.0, -1.0], dtype=p.vertex_accel.dtype)
        via_vertices = sim.simulate(p, 6)
    assert torch.allclose(via_field, via_vertices, atol=1e-12)
    assert float((via_field[-1] - via_field[0]).norm()) > 1e-3


def test_the_field_gets_gradients_and_is_held_before_a_window():
    from saft.reconstruct.window_hold import outside_window, restore_outside_window

    sim, state = _sim_and_state(ShapeConfig(lr_field_accel=1.0, window=2))
    p = state.params
    sim.simulate(p, 6)[-1].sum().backward()
    assert p.field_accel.grad is not None and float(p.field_accel.grad.abs().sum()) > 0
    for t in p.tensors().values():
        t.grad = torch.ones_like(t)
    state.optimizer.step()
    before = p.field_accel.detach().clone()
    for t in p.tensors().values():
        t.grad = torch.zeros_like(t)
    p.field_accel.grad[3:] = 1.0
    keep = outside_window(p, 3)
    state.optimizer.step()
    restore_outside_window(p, 3, keep)
    assert torch.equal(p.field_accel[:3], before[:3])
    assert not torch.equal(p.field_accel[3:], before[3:])


def test_a_checkpointed_state_with_the_field_restores_it():
    from saft.reconstruct.shape_phase import restore_shape_state

    cfg = ShapeConfig(lr_field_accel=1.0)
    _, state = _sim_and_state(cfg)
    with torch.no_grad():
        state.params.field_accel.fill_(0.25)
    restored = restore_shape_state(state.state_dict(), cfg, "cpu")
    assert torch.equal(restored.params.field_accel, state.params.field_accel)
    assert restored.params.field_accel.requires_grad


@pytest.mark.parametrize("weight, expected", [(0.0, 0.0), (1.0, 2.0), (0.5, 1.0)])
def test_force_regularizer_weights_the_component_along_the_viewing_ray(weight, expected):
    from saft.reconstruct.losses import force_regularizer

    accel = torch.tensor([[[0.0, 0.0, 2.0]]], dtype=torch.float64)       # along the ray to the vertex
    positions = torch.tensor([[[0.0, 0.0, 1.0]]], dtype=torch.float64)
    camera = torch.zeros(3, dtype=torch.float64)
    assert float(force_regularizer(accel, positions, camera, weight)) == pytest.approx(expected)


def test_the_along_ray_weight_of_r_f_depends_on_whether_vertices_are_pinned():
    from saft.reconstruct.shape_phase import along_ray_weight

    cfg = ShapeConfig(force_along_weight=0.8, force_along_weight_pinned=0.1)
    free, _ = _sim_and_state(cfg)
    held, _ = _sim_and_state(cfg, pinned=np.arange(5))
    assert along_ray_weight(cfg, free) == 0.8
    assert along_ray_weight(cfg, held) == 0.1
    assert along_ray_weight(ShapeConfig(), free) == 1.0 and along_ray_weight(ShapeConfig(), held) == 0.0


def test_the_light_exists_only_at_a_positive_rate_and_is_restored_from_a_checkpoint():
    from saft.reconstruct.shape_phase import restore_shape_state

    _, off = _sim_and_state(ShapeConfig(lr_light=0.0))
    assert off.params.light is None and "light" not in off.params.tensors()
    cfg = ShapeConfig(lr_light=0.05)
    _, on = _sim_and_state(cfg)
    assert torch.equal(on.params.light, torch.zeros(3, dtype=torch.float64))   # zero light: the unlit renderer
    assert "light" in on.params.tensors() and on.params.light.requires_grad
    with torch.no_grad():
        on.params.light += torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    back = restore_shape_state(on.state_dict(), cfg, "cpu")
    assert torch.equal(back.params.light, on.params.light) and back.params.light.requires_grad


def test_anchors_exist_where_nothing_is_pinned_start_held_and_survive_a_checkpoint():
    from saft.reconstruct.shape_phase import anchors_on, initial_const_accel, new_shape_state, restore_shape_state

    cfg = ShapeConfig(anchors="auto", anchor_log10_init=9.0)
    assert anchors_on(None, cfg) and anchors_on(np.zeros(0, dtype=int), cfg)
    assert not anchors_on(np.arange(3), cfg)
    assert anchors_on(np.arange(3), ShapeConfig(anchors="on")) and not anchors_on(None, ShapeConfig(anchors="off"))
    g = np.array([0.0, -9.81, 0.0])
    assert np.array_equal(initial_const_accel(g, None, cfg), g)   # anchored: the cloth hangs under gravity
    assert np.array_equal(initial_const_accel(g, None, ShapeConfig(anchors="off")), np.zeros(3))
    assert not anchors_on(None, cfg, gravity_stated=False)          # a guessed gravity: the floating cloth
    assert np.array_equal(initial_const_accel(g, None, cfg, gravity_stated=False), np.zeros(3))
    assert anchors_on(None, ShapeConfig(anchors="on"), gravity_stated=False)
    state = new_shape_state(6, 36, g, PhysicsConfig(), cfg, "cpu", anchors=True)
    a = state.params.anchor_log10
    assert a.shape == (36,) and a.requires_grad and torch.equal(a, torch.full((36,), 9.0, dtype=torch.float64))
    assert "anchor_log10" in state.params.tensors()
    assert "anchor_log10" not in new_shape_state(6, 36, g, PhysicsConfig(), cfg, "cpu").params.tensors()
    with torch.no_grad():
        a[:5] = 2.0
    back = restore_shape_state(state.state_dict(), cfg, "cpu")
    assert torch.equal(back.params.anchor_log10, a) and back.params.anchor_log10.requires_grad


def test_held_share_is_linear_in_log_stiffness_up_to_held_and_flat_above():
    from saft.reconstruct.shape_phase import ShapeSimulator, ShapeParams
    from saft.synthetic import grid_template

    mesh = grid_template(2, 0.3)
    sim = ShapeSimulator(torch.tensor(mesh.vertices), mesh.quads, PhysicsConfig(substeps=4), 0.02, None)
    held_at = np.log10(10.0 / 0.005 ** 2)   # w h² = 10 with h = 5 ms
    zero = torch.zeros((), dtype=torch.float64)

    def share(values):
        u = torch.tensor(values, dtype=torch.float64, requires_grad=True)
        p = ShapeParams(zero, zero, zero, torch.zeros(3, dtype=torch.float64), torch.zeros(1, 9, 3), anchor_log10=u)
        s = sim.held_share(p, floor=0.0)
        s.backward()
        return float(s.detach()), u.grad

    assert share([0.0] * 9)[0] == 0.0
    assert share([held_at / 2] * 9)[0] == pytest.approx(0.5)
    value, grad = share([held_at + 3.0] * 8 + [held_at / 4])
    assert value == pytest.approx((8 + 0.25) / 9)
    assert torch.all(grad[:8] == 0) and grad[8] > 0   # a held vertex feels no pull from the penalty
    assert float(sim.held_share(ShapeParams(zero, zero, zero, torch.zeros(3), torch.zeros(1, 9, 3)), 0.0)) == 0.0

