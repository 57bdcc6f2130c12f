"""physics.air_drag in the shape phase: off at 0, learned in log10 where on, checkpointed, in the rollout."""

import math

import numpy as np
import pytest
import torch

from saft.errors import SaftInputError
from saft.reconstruct.config import PhysicsConfig, SaftConfig, ShapeConfig
from saft.reconstruct.config_checks import check_config_ranges
from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state, restore_shape_state
from saft.synthetic import grid_template


def _setup(phys, cfg=None, frames=6):
    mesh = grid_template(4, 0.3)   # in the plane z = 0: gravity along -z falls along its normal
    template = torch.tensor(mesh.vertices)
    sim = ShapeSimulator(template, mesh.quads, phys, 0.02, None)
    state = new_shape_state(frames, len(template), np.array([0.0, 0.0, -9.81]), phys, cfg or ShapeConfig(), "cpu")
    return sim, state


def test_off_at_zero_and_learned_from_the_prior_where_on():
    assert PhysicsConfig().air_drag == 0.6   # the default: on, then kept or dropped by air_drag_where
    _, off = _setup(PhysicsConfig(air_drag=0.0))
    assert off.params.log10_drag is None and "log10_drag" not in off.params.tensors()
    assert "log10_drag" not in off.optimizer.specs
    _, on = _setup(PhysicsConfig(air_drag=0.6))
    d = on.params.log10_drag
    assert d.requires_grad and float(d.detach()) == pytest.approx(math.log10(0.6))
    assert on.optimizer.specs["log10_drag"].lr == ShapeConfig().lr_air_drag
    _, held = _setup(PhysicsConfig(air_drag=0.6), ShapeConfig(lr_air_drag=0.0))
    assert "log10_drag" not in held.optimizer.specs
    back = restore_shape_state(on.state_dict(), ShapeConfig(), "cpu")
    assert torch.equal(back.params.log10_drag, d) and "log10_drag" in back.optimizer.specs


def test_the_drag_reaches_the_rollout_and_gets_a_gradient():
    sim, off = _setup(PhysicsConfig(air_drag=0.0))
    _, on = _setup(PhysicsConfig(air_drag=2.0))
    x_off = sim.simulate(off.params, 6).detach()
    x_on = sim.simulate(on.params, 6)
    fall_off = float(x_off[0, :, 2].mean() - x_off[-1, :, 2].mean())
    fall_on = float(x_on[0, :, 2].mean() - x_on[-1, :, 2].mean())
    assert 0 < fall_on < 0.99 * fall_off   # falling along its normal: braked
    x_on[-1, :, 2].sum().backward()
    assert on.params.log10_drag.grad is not None and float(on.params.log10_drag.grad) > 0


def test_config_checks_the_drag_and_its_range():
    cfg = SaftConfig()
    check_config_ranges(cfg)
    cfg.physics.air_drag = 0.6
    check_config_ranges(cfg)
    cfg.physics.air_drag = 50.0
    with pytest.raises(SaftInputError, match="air_drag"):
        check_config_ranges(cfg)
    cfg.physics.air_drag = 0.0
    cfg.physics.air_drag_range = (0.0, 1.0)
    with pytest.raises(SaftInputError, match="air_drag_range"):
        check_config_ranges(cfg)


def test_the_swing_gate_drops_the_drag_where_the_default_damping_is_kept(monkeypatch):
    import saft.reconstruct.air_drag as ad

    seen = []

    def fake_run_damping(chosen):
        def run(state, sim, tracks, camera, phys):
            seen.append(state.params.log10_drag)   # the trial runs without the drag
            return chosen
        return run

    for where, chosen, kept in (("swing", 0.9, False), ("swing", 0.99, True), ("always", 0.9, True)):
        phys = PhysicsConfig(air_drag=0.6, air_drag_where=where)
        sim, state = _setup(phys)
        monkeypatch.setattr(ad, "run_damping", fake_run_damping(chosen))
        assert ad.run_damping_and_drag(state, sim, None, None, phys) == chosen
        assert seen.pop() is None
        assert (state.params.log10_drag is not None) == kept
        assert ("log10_drag" in state.optimizer.specs) == kept
        assert ("log10_drag" in state.state_dict()["params"]) == kept
    # off (air_drag = 0): nothing to drop
    phys = PhysicsConfig(air_drag=0.0)
    sim, state = _setup(phys)
    monkeypatch.setattr(ad, "run_damping", fake_run_damping(0.9))
    assert ad.run_damping_and_drag(state, sim, None, None, phys) == 0.9 and state.params.log10_drag is None
