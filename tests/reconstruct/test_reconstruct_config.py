import pytest

from saft.cli import main
from saft.config_io import from_dict, load_config, to_toml
from saft.errors import SaftInputError
from saft.reconstruct import SaftConfig


def test_defaults_are_the_published_ones():
    c = SaftConfig()
    assert c.texture.epochs == 200 and c.texture.size == 512 and c.texture.lambda_smooth == 1e-4
    assert c.shape.lambda_sil == 0.2 and c.shape.lambda_energy == 2.0 and c.shape.lambda_force == 2e-4
    assert c.shape.lr_vertex_accel == 0.2 and c.shape.lr_const_accel == 0.1 and c.shape.lr_stiffness == 0.02
    assert c.physics.substeps == 4 and c.physics.log10_Y_range == (1.0, 3.0)


def test_toml_round_trip(tmp_path):
    c = load_config(SaftConfig, None, ["shape.lambda_force=0", "texture.epochs=7", 'run.device="cpu"'])
    assert c.shape.lambda_force == 0.0 and c.texture.epochs == 7 and c.run.device == "cpu"
    path = tmp_path / "c.toml"
    path.write_text(to_toml(c))
    assert load_config(SaftConfig, path) == c


@pytest.mark.parametrize("override, message", [
    ("shape.lambda_forc=1", "unknown config key 'shape.lambda_forc'"),
    ("nosuch.x=1", "unknown config key 'nosuch'"),
    ("texture.epochs=1.5", "texture.epochs must be an integer"),
    ("shape.enabled=3", "shape.enabled must be true or false"),
    ('run.device="gpu"', "run.device must be one of"),
    ("physics.log10_Y_range=[1]", "must have 2 elements"),
    ("shape.anchor_log10_range=[5, 1]", "shape.anchor_log10_range must be [low, high]"),
    ("shape.anchor_log10_init=12", "shape.anchor_log10_init = 12.0 lies outside"),
    ("shape.lambda_anchor=-1", "shape.lambda_anchor must lie in"),
    ('shape.anchors="maybe"', "shape.anchors must be one of"),
])
def test_bad_overrides_are_rejected(override, message):
    from saft.reconstruct.config import load_saft_config   # the types (load_config) and the ranges

    with pytest.raises(SaftInputError, match=message.replace("(", r"\(").replace("[", r"\[")):
        load_saft_config(None, [override])


def test_bad_config_file_names_the_file(tmp_path, capsys, native_scene):
    bad = tmp_path / "bad.toml"
    bad.write_text("[shape]\nlambda_sil = 'a lot'\n")
    code = main(["reconstruct", str(native_scene), "--out", str(tmp_path / "out"), "--config", str(bad)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and str(bad) in err and "shape.lambda_sil must be a number" in err
    assert len(err.splitlines()) == 1
    broken = tmp_path / "broken.toml"
    broken.write_text("[shape\n")
    assert main(["reconstruct", str(native_scene), "--out", str(tmp_path / "o2"), "--config", str(broken)]) == 2
    assert "not valid TOML" in capsys.readouterr().err


def test_section_must_be_a_table():
    with pytest.raises(SaftInputError, match="section shape must be a table"):
        from_dict(SaftConfig, {"shape": 3})


def test_appearance_profile_resolves_to_cpu_with_user_values_on_top():
    from saft.reconstruct.config import load_saft_config

    c = load_saft_config(None, ['run.device="cpu"', "appearance.epochs=7"])
    assert c.appearance.profile == "cpu" and c.appearance.epochs == 7
    assert c.appearance.frames_per_epoch > 0 and c.appearance.image_scale < 1   # from the CPU profile
    with pytest.raises(SaftInputError, match="appearance.maps"):
        load_saft_config(None, ['run.device="cpu"', 'appearance.maps="pixels"'])


def test_physics_hessian_reaches_the_simulator():
    """physics.hessian selects the implicit step's element Hessians: the two modes simulate differently."""
    import numpy as np
    import torch

    from saft.reconstruct.shape_phase import ShapeSimulator, new_shape_state
    from saft.synthetic.hanging_cloth import grid_template

    with pytest.raises(SaftInputError, match="physics.hessian must be one of"):
        load_config(SaftConfig, None, ['physics.hessian="diagonal"'])
    template = grid_template(6, 0.2)
    x0 = torch.as_tensor(template.vertices, dtype=torch.float64)
    runs = {}
    for mode in ("projected", "exact"):
        cfg = load_config(SaftConfig, None, [f'physics.hessian="{mode}"'])
        sim = ShapeSimulator(x0, template.quads, cfg.physics, 0.02, None)
        state = new_shape_state(4, len(x0), np.zeros(3), cfg.physics, cfg.shape, "cpu")
        with torch.no_grad():
            state.params.vertex_accel.copy_(torch.randn(state.params.vertex_accel.shape,
                                                        generator=torch.Generator().manual_seed(0)) * 20)
            runs[mode] = sim.simulate(state.params, 4)
    assert torch.isfinite(runs["exact"]).all()
    assert (runs["exact"] - runs["projected"]).abs().max() > 1e-6



def test_physics_rest_shape_reaches_the_simulator():
    import math

    import numpy as np
    import torch

    from saft.reconstruct.shape_phase import ShapeSimulator
    from saft.synthetic.hanging_cloth import grid_template

    with pytest.raises(SaftInputError, match="physics.rest_shape must be one of"):
        load_config(SaftConfig, None, ['physics.rest_shape="curved"'])
    template = grid_template(6, 0.2)
    x0 = torch.as_tensor(template.vertices, dtype=torch.float64).clone()
    x0[:, 2] += 0.03 * torch.sin(20 * x0[:, 1])  # billowed: the template is not flat
    angles = {}
    for shape in ("template", "flat", "moving"):
        cfg = load_config(SaftConfig, None, [f'physics.rest_shape="{shape}"'])
        sim = ShapeSimulator(x0, template.quads, cfg.physics, 0.02, None)
        t = sim.topology
        angles[shape] = t.rest_angle[t.is_bend].numpy()
    assert SaftConfig().physics.rest_shape == "moving"
    assert angles["template"].max() > math.acos(0.99) + 0.01
    assert np.allclose(angles["flat"], math.acos(0.99), atol=1e-9)
    # "moving" starts from the template's rest shape; the shape phase flattens it once the v0 gate finds the
    # clip in motion (run_shape_phase), through use_rest_shape
    assert np.array_equal(angles["moving"], angles["template"])
    sim.use_rest_shape("flat")
    flat = sim.topology
    assert np.allclose(flat.rest_angle[flat.is_bend].numpy(), math.acos(0.99), atol=1e-9)
    sim.use_rest_shape("flat")   # unchanged: the topology is kept, not rebuilt
    assert sim.topology is flat
