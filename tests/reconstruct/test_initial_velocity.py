"""The learned velocity at frame 0 (saft.reconstruct.initial_velocity) and how the shape phase uses it."""

import numpy as np
import torch

from saft.reconstruct.config import PhysicsConfig, ShapeConfig
from saft.reconstruct.initial_velocity import initial_velocity, velocity_prior


def _sim_and_state(cfg, frames=6):
    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.synthetic import grid_template

    mesh = grid_template(5, 0.3)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 0.02, None)
    return sim, new_shape_state(frames, len(template), np.zeros(3), PhysicsConfig(), cfg, "cpu")


def test_off_by_default_off_at_rate_zero_and_at_rest_at_first():
    sim, off = _sim_and_state(ShapeConfig(lr_v0=0.0))
    assert off.params.velocity(sim.field_basis) is None and "v0_field" not in off.params.tensors()
    assert _sim_and_state(ShapeConfig())[1].params.v0_field is None
    sim, on = _sim_and_state(ShapeConfig(lr_v0=0.1))
    with torch.no_grad():
        assert torch.equal(sim.simulate(on.params, 4), sim.simulate(off.params, 4))
    assert float(velocity_prior(on.params.velocity(sim.field_basis), sim.template).detach()) == 0.0


def test_a_uniform_field_is_the_same_per_vertex_velocity_and_moves_the_cloth():
    basis = torch.rand(9, 4, dtype=torch.float64)
    basis[:, 0] = 1.0
    field = torch.zeros(4, 3, dtype=torch.float64)
    field[0] = torch.tensor([0.0, 0.0, 1.0])
    v = initial_velocity(field, basis)
    assert torch.allclose(v, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(9, 3))
    assert float(velocity_prior(v, v)) == 1.0
    sim, state = _sim_and_state(ShapeConfig(lr_v0=0.1))
    with torch.no_grad():
        state.params.v0_field[0, 2] = 1.0
        x = sim.simulate(state.params, 3)
    assert float((x[1] - x[0])[:, 2].mean()) > 0.01   # moved towards +z in one frame of 0.02 s


def test_v0_gets_gradients_full_and_windowed_agree_and_a_window_holds_it():
    from saft.reconstruct.window_hold import outside_window, restore_outside_window

    sim, state = _sim_and_state(ShapeConfig(lr_v0=0.1, window=2))
    p = state.params
    with torch.no_grad():
        p.v0_field[0] = torch.tensor([0.1, 0.2, 0.3], dtype=p.v0_field.dtype)
    full = sim.simulate(p, 4)
    stepped, _ = sim.simulate_from(p, 0, 4)   # start 0, no stored state: the learned v0
    assert torch.allclose(full, stepped, atol=1e-10)
    full[-1].sum().backward()
    assert float(p.v0_field.grad.abs().sum()) > 0
    before = p.v0_field.detach().clone()
    for t in p.tensors().values():
        t.grad = torch.ones_like(t)
    keep = outside_window(p, 3)
    state.optimizer.step()
    restore_outside_window(p, 3, keep)
    assert torch.equal(p.v0_field, before)


def test_a_checkpointed_state_restores_v0():
    from saft.reconstruct.shape_phase import restore_shape_state

    cfg = ShapeConfig(lr_v0=0.1)
    _, state = _sim_and_state(cfg)
    with torch.no_grad():
        state.params.v0_field[1, 2] = 0.5
    back = restore_shape_state(state.state_dict(), cfg, "cpu")
    assert torch.equal(back.params.v0_field, state.params.v0_field) and back.params.v0_field.requires_grad


def test_field_from_tracks_recovers_an_in_plane_motion():
    from saft.reconstruct.force_field import affine_basis
    from saft.reconstruct.initial_velocity import field_from_tracks
    from saft.reconstruct.tracks import VertexTracks, project
    from saft.scene.camera import look_at
    from saft.synthetic import grid_template

    template = torch.tensor(grid_template(6, 0.4).vertices)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    camera = look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), K, 320, 240)
    basis = affine_basis(template)
    truth = torch.zeros(4, 3, dtype=torch.float64)
    truth[0, :2] = torch.tensor([0.3, -0.2])    # a translation in the image plane
    truth[1, 1] = 0.4                           # and a shear: the right side rises faster
    dt = 1 / 30
    moved = template + dt * initial_velocity(truth, basis)
    points = torch.stack([project(template, camera)[0], project(moved, camera)[0]])
    tracks = VertexTracks(points, torch.ones(2, len(template), dtype=torch.bool), 320.0)
    got = field_from_tracks(tracks, template, camera, dt, basis, ridge=1e-6)
    assert torch.allclose(got[:2, :2], truth[:2, :2], atol=0.02)
    tracks.valid[1] = False
    assert field_from_tracks(tracks, template, camera, dt, basis) is None
