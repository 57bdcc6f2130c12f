"""The silhouette weight of a swinging run (saft.reconstruct.swing_weights)."""

import pytest

from saft.reconstruct.config import PhysicsConfig, SaftConfig, ShapeConfig


def test_off_and_the_config_unchanged_where_the_run_keeps_the_default_damping():
    from saft.reconstruct.swing_weights import swing_shape_config

    phys = PhysicsConfig()
    assert ShapeConfig().swing_lambda_sil == 1.0                              # the default
    off = ShapeConfig(swing_lambda_sil=0.0)
    assert swing_shape_config(off, phys, phys.swing_damping) is off           # off: even in a swing
    on = ShapeConfig(swing_lambda_sil=1.0)
    assert swing_shape_config(on, phys, phys.damping) is on                   # no swing: the same object


def test_a_swinging_run_takes_swing_lambda_sil_and_nothing_else_changes():
    import dataclasses

    from saft.reconstruct.swing_weights import swing_shape_config

    phys = PhysicsConfig(swing_run_damping=0.995)
    on = ShapeConfig(swing_lambda_sil=1.0)
    for damping in (phys.swing_damping, phys.swing_run_damping):             # the trial's pick, or run lower
        swung = swing_shape_config(on, phys, damping)
        assert swung.lambda_sil == 1.0 and on.lambda_sil == ShapeConfig().lambda_sil   # a copy; cfg untouched
        assert dataclasses.replace(swung, lambda_sil=on.lambda_sil) == on


def test_swing_lambda_sil_is_range_checked():
    from saft.errors import SaftInputError
    from saft.reconstruct.config_checks import check_config_ranges

    cfg = SaftConfig()
    cfg.shape.swing_lambda_sil = -1.0
    with pytest.raises(SaftInputError):
        check_config_ranges(cfg)
