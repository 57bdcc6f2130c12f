"""The damping lowered by a trial where the clip swings under gravity (saft.reconstruct.swing_damping)."""

import numpy as np
import torch

from saft.reconstruct.config import PhysicsConfig, ShapeConfig


def _corner(frames=10):
    """A 6 × 6 cloth in the xy plane held at its top-left corner (gravity -y), 30 fps, a camera at 1.2 m."""
    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.scene.camera import look_at
    from saft.synthetic import grid_template

    mesh = grid_template(6, 0.4)
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, PhysicsConfig(), 1 / 30, np.array([0, 1, 6, 7]))
    state = new_shape_state(frames, len(template), np.array([0.0, -9.81, 0.0]), PhysicsConfig(), ShapeConfig(lr_v0=0),
                            "cpu")
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    camera = look_at((0.2, 0.0, 1.2), (0.0, -0.1, 0.0), (0.0, 1.0, 0.0), K, 320, 240)
    return sim, state, camera


def _tracks_of(positions, camera):
    from saft.reconstruct.tracks import VertexTracks, project

    points = torch.stack([project(p, camera)[0] for p in positions])
    return VertexTracks(points, torch.ones(points.shape[:2], dtype=torch.bool), 320.0)


def _swing(sim, state, damping, frames=10):
    sim.damping = damping
    with torch.no_grad():
        x = sim.simulate(state.params, frames)
    sim.damping = PhysicsConfig().damping
    return x


def test_a_swing_under_gravity_takes_the_low_damping_and_a_cloth_at_rest_the_default():
    from saft.reconstruct.swing_damping import choose_damping

    sim, state, camera = _corner()
    default = PhysicsConfig().damping
    swinging = _swing(sim, state, 0.99)
    assert float((swinging[-1] - swinging[0]).norm(dim=-1).max()) > 0.1   # a real swing, not a sag
    assert choose_damping(sim, state.params, _tracks_of(swinging, camera), camera, default, 0.99) == 0.99
    assert sim.damping == default                                         # the trial leaves the simulator as it was
    braked = _swing(sim, state, default)                                  # what the paper's damping makes of it
    assert choose_damping(sim, state.params, _tracks_of(braked, camera), camera, default, 0.99) == default
    still = sim.template.expand(10, -1, -1)                               # the video shows no motion
    assert choose_damping(sim, state.params, _tracks_of(still, camera), camera, default, 0.99) == default
    assert choose_damping(sim, state.params, _tracks_of(swinging, camera), camera, default, 0.0) == default   # off


def test_the_choice_is_checkpointed_a_resumed_run_keeps_it_and_the_force_rates_fall_with_it():
    from saft.reconstruct.shape_phase import restore_shape_state
    from saft.reconstruct.swing_damping import FORCE_RATES, rate_scale, run_damping

    sim, state, camera = _corner()
    assert state.damping is None   # chosen at epoch 0
    rates = {n: s.lr for n, s in state.optimizer.specs.items()}
    phys = PhysicsConfig(swing_damping=0.99, swing_run_damping=0.0)   # the trial alone
    state.damping = run_damping(state, sim, _tracks_of(_swing(sim, state, 0.99), camera), camera, phys)
    assert state.damping == 0.99
    scale = rate_scale(PhysicsConfig().damping, 0.99)
    assert {"const_accel", "vertex_accel", "field_accel"} <= set(FORCE_RATES) and abs(scale - 0.1) < 1e-12
    for name, spec in state.optimizer.specs.items():
        assert spec.lr == (rates[name] * scale if name in FORCE_RATES else rates[name]), name
    back = restore_shape_state(state.state_dict(), ShapeConfig(lr_v0=0), "cpu")   # a new optimizer, cfg's rates
    assert back.damping == 0.99
    still = _tracks_of(sim.template.expand(10, -1, -1), camera)        # not chosen again from other evidence
    assert run_damping(back, sim, still, camera, phys) == 0.99
    assert back.optimizer.specs["vertex_accel"].lr == rates["vertex_accel"] * scale
    _, fresh, _ = _corner()
    assert run_damping(fresh, sim, still, camera, phys) == phys.damping    # at rest: the default, rates kept
    assert {n: s.lr for n, s in fresh.optimizer.specs.items()} == rates


def test_params_json_names_the_damping_the_run_used():
    from saft.reconstruct.config import SaftConfig
    from saft.reconstruct.pipeline import shape_params_summary

    _, state, _ = _corner()
    scene = type("S", (), {"frame_dt": 1 / 30})()
    assert shape_params_summary(state.state_dict(), SaftConfig(), scene)["damping"] == PhysicsConfig().damping
    state.damping = 0.99
    assert shape_params_summary(state.state_dict(), SaftConfig(), scene)["damping"] == 0.99


def test_swing_run_damping_replaces_the_trials_pick_only_where_the_trial_picks_it():
    from saft.reconstruct.shape_phase import restore_shape_state
    from saft.reconstruct.swing_damping import FORCE_RATES, rate_scale, run_damping

    assert PhysicsConfig().swing_run_damping == 0.995                      # the default
    sim, state, camera = _corner()
    rates = {n: s.lr for n, s in state.optimizer.specs.items()}
    phys = PhysicsConfig(swing_damping=0.99, swing_run_damping=0.995)
    swinging = _tracks_of(_swing(sim, state, 0.99), camera)
    state.damping = run_damping(state, sim, swinging, camera, phys)
    assert state.damping == 0.995
    scale = rate_scale(phys.damping, 0.995)
    assert abs(scale - 0.05) < 1e-12
    for name, spec in state.optimizer.specs.items():
        assert abs(spec.lr - (rates[name] * scale if name in FORCE_RATES else rates[name])) < 1e-15, name
    back = restore_shape_state(state.state_dict(), ShapeConfig(lr_v0=0), "cpu")   # a resumed run keeps it
    assert run_damping(back, sim, swinging, camera, phys) == 0.995
    _, still_state, _ = _corner()                                          # the trial keeps the default there
    still = _tracks_of(sim.template.expand(10, -1, -1), camera)
    assert run_damping(still_state, sim, still, camera, phys) == phys.damping
    assert {n: s.lr for n, s in still_state.optimizer.specs.items()} == rates
    _, off_state, _ = _corner()                                            # off: the trial's own pick
    off = PhysicsConfig(swing_damping=0.99, swing_run_damping=0.0)
    assert run_damping(off_state, sim, swinging, camera, off) == 0.99


def test_swing_run_damping_is_range_checked():
    import pytest

    from saft.errors import SaftInputError
    from saft.reconstruct.config import SaftConfig
    from saft.reconstruct.config_checks import check_config_ranges

    cfg = SaftConfig()
    cfg.physics.swing_run_damping = 1.5
    with pytest.raises(SaftInputError):
        check_config_ranges(cfg)
