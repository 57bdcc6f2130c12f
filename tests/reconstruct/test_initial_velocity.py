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


def test_on_by_default_off_at_rate_zero_and_at_rest_at_first():
    sim, off = _sim_and_state(ShapeConfig(lr_v0=0.0))
    assert off.params.velocity(sim.field_basis) is None and "v0_field" not in off.params.tensors()
    assert ShapeConfig().lr_v0 == 0.02 and _sim_and_state(ShapeConfig())[1].params.v0_field is not None
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


def test_start_motion_recovers_an_in_plane_motion():
    from saft.reconstruct.force_field import affine_basis
    from saft.reconstruct.initial_velocity import start_motion
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
    got = start_motion(tracks, template, camera, dt, basis, ridge=1e-6).field
    assert torch.allclose(got[:2, :2], truth[:2, :2], atol=0.02)
    tracks.valid[1] = False
    assert start_motion(tracks, template, camera, dt, basis) is None


def _hanging(frames=4, anchors=False):
    """A free 6 × 6 cloth in the xy plane pushed along -z (a constant acceleration of 9.81 m/s²: its first
    step from rest leaves the plane), a camera 1.4 m away at 45°, and a fresh state."""
    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.scene.camera import look_at
    from saft.synthetic import grid_template

    mesh = grid_template(6, 0.4)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 1 / 30, None)
    state = new_shape_state(frames, len(template), np.array([0.0, 0.0, -9.81]), PhysicsConfig(),
                            ShapeConfig(lr_v0=0.02), "cpu", anchors=anchors)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    camera = look_at((1.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), K, 320, 240)
    return sim, state, camera


def _tracks_of(positions, camera):
    from saft.reconstruct.tracks import VertexTracks, project

    points = torch.stack([project(p, camera)[0] for p in positions])
    return VertexTracks(points, torch.ones(points.shape[:2], dtype=torch.bool), 320.0)


def test_a_clip_that_starts_at_rest_drops_v0_even_when_its_first_step_moves():
    from saft.reconstruct.initial_velocity import start_velocity

    sim, state, camera = _hanging()
    with torch.no_grad():
        falling = sim.simulate(state.params, 4)          # from rest: pushed back along -z
    assert float((falling[1] - falling[0]).norm(dim=-1).max()) > 3e-3
    motion = start_velocity(state.params, state.optimizer, sim, _tracks_of(falling, camera), camera)
    assert motion is not None and not motion.moving
    assert motion.fitted_px < 0.01 * motion.median_px    # the physics from rest explains the step
    assert state.params.v0_field is None and "v0_field" not in state.params.tensors()
    assert "v0_field" not in state.optimizer.specs and "v0_field" not in state.optimizer.state_dict()["optims"]
    with torch.no_grad():                                # the run goes on as with shape.lr_v0 = 0
        assert torch.equal(sim.simulate(state.params, 4), falling)

    sim, state, camera = _hanging(frames=1)              # no tracks (one frame): no evidence of motion
    assert start_velocity(state.params, state.optimizer, sim, None, camera) is None
    assert state.params.v0_field is None


def test_a_clip_that_starts_moving_is_seeded_with_the_motion_beyond_the_physics_from_rest():
    from saft.reconstruct.initial_velocity import start_velocity

    sim, state, camera = _hanging()
    truth = torch.zeros(4, 3, dtype=torch.float64)
    truth[0, :2] = torch.tensor([0.3, -0.2])             # sideways and down
    with torch.no_grad():
        state.params.v0_field.copy_(truth)
        moving = sim.simulate(state.params, 4)
        state.params.v0_field.zero_()
    motion = start_velocity(state.params, state.optimizer, sim, _tracks_of(moving, camera), camera)
    assert motion.moving and motion.fitted_px > 5 * motion.rest_px
    assert "v0_field" in state.optimizer.specs
    seed = state.params.v0_field.detach()
    # the image sees the step after the solver's damping, and x partly along the rays (the ridge keeps that
    # part small): the seed points the true way, within 25 % in y
    assert float(seed[0, 0]) > 0.05 and -0.25 < float(seed[0, 1]) < -0.15 and float(seed[1:].abs().max()) < 0.05


def test_soft_anchors_drop_v0_even_where_the_clip_starts_moving():
    from saft.reconstruct.initial_velocity import start_velocity

    sim, free, camera = _hanging()
    truth = torch.zeros(4, 3, dtype=torch.float64)
    truth[0, :2] = torch.tensor([0.3, -0.2])
    with torch.no_grad():
        free.params.v0_field.copy_(truth)
        moving = sim.simulate(free.params, 4)            # tracks of a cloth that starts moving
    _, state, _ = _hanging(anchors=True)
    motion = start_velocity(state.params, state.optimizer, sim, _tracks_of(moving, camera), camera)
    assert motion.moving                                 # the gate alone would learn it
    assert state.params.v0_field is None and "v0_field" not in state.optimizer.specs


def test_the_gate_needs_a_share_of_the_clips_motion_and_a_margin_over_the_noise():
    from saft.reconstruct.initial_velocity import MIN_SHARE, MIN_SNR, StartMotion

    def motion(fitted, rest, median):
        return StartMotion(torch.zeros(4, 3), fitted, rest, median).moving

    assert motion(1.0, 0.1, 1.0)
    assert not motion(0.06, 0.015, 0.53)                 # the demo's numbers: coherent, but 0.11 of the clip
    assert not motion(1.0, 1.0 / (0.9 * MIN_SNR), 1.0)   # below the noise margin
    assert not motion(1.0, 0.1, 1.0 / (0.9 * MIN_SHARE))
    assert motion(1.0, 1.0 / (1.1 * MIN_SNR), 1.0 / (1.1 * MIN_SHARE))


def test_a_checkpoint_with_v0_dropped_restores_without_it():
    from saft.reconstruct.initial_velocity import start_velocity
    from saft.reconstruct.shape_phase import restore_shape_state

    sim, state, camera = _hanging()
    with torch.no_grad():
        falling = sim.simulate(state.params, 4)
    start_velocity(state.params, state.optimizer, sim, _tracks_of(falling, camera), camera)
    back = restore_shape_state(state.state_dict(), ShapeConfig(lr_v0=0.02), "cpu")
    assert back.params.v0_field is None and "v0_field" not in back.optimizer.specs
