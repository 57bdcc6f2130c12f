"""Metal or not per cluster after the fit (appearance.metal_decide)."""

import numpy as np
import pytest
import torch

from saft.appearance.config import AppearanceConfig
from saft.appearance.guided import GuidedMaps
from saft.appearance.metal_decide import decide_metals, held_out_frames, ramp_metallic
from saft.appearance.params import EnvironmentMap

torch.set_num_threads(1)


def _model(metallic=0.3):
    tex = np.full((16, 16, 3), [0.08, 0.06, 0.02], np.float32)   # dark gold (a metal's frame-0 diffuse)
    tex[:, 8:] = [0.05, 0.06, 0.18]                              # dark blue cloth
    model = GuidedMaps(tex, size=16, gain_grid=2, clusters=2, init_roughness=0.3, init_metallic=metallic)
    gold = int(model.members[:, 0, 0].argmax())
    model.use_metal_colour(rate=3.0, allowed=np.arange(2) == gold)
    return model, gold, tex


def _loss_to(target):
    """A 'render' that is the base colour itself: the loss is its squared distance to target (S, S, 3)."""
    target = torch.as_tensor(target)
    return lambda f, maps, env, spp, seed: ((maps["diffuse"] - target) ** 2).mean()


def _env():
    return EnvironmentMap(4, 8, 0.5, 0.01)


def test_held_out_frames_split_the_clip():
    train, held = held_out_frames(32)
    assert len(held) == 8 and held[0] == 0 and held[-1] == 31 and not set(train) & set(held)
    assert sorted(train + held) == list(range(32))
    assert held_out_frames(4) == ([0, 1, 2, 3], [0, 1, 2, 3])   # nothing left to refit on: all of them


def test_a_bright_gold_cluster_becomes_metal_and_a_dark_one_stays_as_fitted():
    model, gold, tex = _model()
    bright = tex.copy()
    bright[:, :8] = [0.9, 0.7, 0.3]   # the frames show the gold cluster as bright as a metal's F0
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=20, lr=0.05, lr_env=0.05)
    assert [r["decision"] for r in rows] == ["metal"] and rows[0]["cluster"] == gold
    assert rows[0]["held_loss_metal"] < rows[0]["held_loss_dielectric"]
    assert model.cluster_values()["metallic"][gold].item() == pytest.approx(1.0, abs=1e-6)

    model, gold, tex = _model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    rows = decide_metals(model, _env(), 1.0, _loss_to(tex), 12, epochs=20, lr=0.05, lr_env=0.05)   # the frames show its texture
    assert [r["decision"] for r in rows] == ["as fitted"] and rows[0]["held_loss_dielectric"] < rows[0]["held_loss_metal"]
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())   # the fit left as it was


def test_only_half_metal_clusters_with_a_metal_colour_are_decided():
    for metallic in (0.01, 0.99):   # already dielectric or metal: left as fitted
        model, gold, tex = _model(metallic)
        before = {k: v.clone() for k, v in model.state_dict().items()}
        assert decide_metals(model, _env(), 1.0, _loss_to(tex), 12, epochs=5, lr=0.05, lr_env=0.05) == []
        assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
    plain = GuidedMaps(_model()[2], size=16, gain_grid=2, clusters=2, init_metallic=0.3)   # no metal colour
    assert decide_metals(plain, _env(), 1.0, _loss_to(_model()[2]), 12, epochs=5, lr=0.05, lr_env=0.05) == []


def test_the_ramp_moves_the_metallic_on_a_line_to_the_pin():
    up = [ramp_metallic(0.2, True, e, 4) for e in range(5)]
    assert up[:3] == pytest.approx([0.4, 0.6, 0.8]) and up[3:] == [None, None]
    assert [ramp_metallic(0.2, False, e, 4) for e in range(3)] == pytest.approx([0.15, 0.1, 0.05])
    assert ramp_metallic(0.2, True, 0, 1) is None   # a ramp of one epoch: pinned at once


def test_a_ramped_refit_ends_pinned_and_finds_the_bright_gold():
    model, gold, tex = _model()
    bright = tex.copy()
    bright[:, :8] = [0.9, 0.7, 0.3]
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10)
    assert [r["decision"] for r in rows] == ["metal"]
    assert model.cluster_values()["metallic"][gold].item() == pytest.approx(1.0, abs=1e-6)
    model, gold, tex = _model()
    rows = decide_metals(model, _env(), 1.0, _loss_to(tex), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10)
    assert [r["decision"] for r in rows] == ["as fitted"]


def test_low_zero_decides_a_metal_coloured_cluster_the_fit_left_dielectric():
    model, gold, tex = _model(0.01)
    bright = tex.copy()
    bright[:, :8] = [0.9, 0.7, 0.3]
    assert decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=5, lr=0.05, lr_env=0.05) == []
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=20, lr=0.05, lr_env=0.05, low=0.0, ramp=10)
    assert [r["cluster"] for r in rows] == [gold] and rows[0]["metallic_fitted"] == pytest.approx(0.01, abs=1e-3)
    assert rows[0]["decision"] == "metal"


def test_glossy_decides_a_glossy_dielectric_with_a_metal_colour_and_leaves_a_rough_one():
    bright = _model()[2].copy()
    bright[:, :8] = [0.9, 0.7, 0.3]
    model, gold, tex = _model(0.01)   # the fit left the gold dielectric, glossy (roughness 0.3)
    assert decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=5, lr=0.05, lr_env=0.05) == []
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10,
                         glossy=0.5)
    assert [(r["cluster"], r["decision"]) for r in rows] == [(gold, "metal")]
    assert rows[0]["metallic_fitted"] == pytest.approx(0.01, abs=1e-3)
    assert model.cluster_values()["metallic"][gold].item() == pytest.approx(1.0, abs=1e-6)

    model, gold, tex = _model(0.01)
    with torch.no_grad():
        model.rough_logit[gold] = 2.2   # roughness 0.9: a rough dielectric is not decided
    before = {k: v.clone() for k, v in model.state_dict().items()}
    assert decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=5, lr=0.05, lr_env=0.05, glossy=0.5) == []
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())

    model, gold, tex = _model(0.01)   # glossy, but its frames show its texture: tested and left as fitted
    before = {k: v.clone() for k, v in model.state_dict().items()}
    rows = decide_metals(model, _env(), 1.0, _loss_to(tex), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10,
                         glossy=0.5)
    assert [r["decision"] for r in rows] == ["as fitted"]
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_a_cluster_below_low_starts_its_metal_refit_with_its_highlights_hue():
    bright = _model()[2].copy()
    bright[:, :8] = [0.9, 0.7, 0.3]
    hues = np.array([[1.0, 0.78, 0.33], [np.nan] * 3])

    def drifted():   # the fit left the gold glossy at metallic 0.01, its metal colour drifted to white
        model, gold, tex = _model(0.01)
        model.metal.set_hue(gold, [1.0, 1.0, 0.95])
        return model, gold, (hues if gold == 0 else hues[::-1])

    model, gold, h = drifted()
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=6, lr=0.05, lr_env=0.05, glossy=0.5, hues=h)
    assert rows[0]["metal_hue_from_highlights"] == pytest.approx(list(h[gold]))
    with_hue = rows[0]["held_loss_metal"]
    c = model.metal.colours()[gold].detach().numpy()
    assert c[2] / c[0] < 0.5   # gold, not the drifted white
    model, gold, h = drifted()
    rows = decide_metals(model, _env(), 1.0, _loss_to(bright), 12, epochs=6, lr=0.05, lr_env=0.05, glossy=0.5)
    assert "metal_hue_from_highlights" not in rows[0] and with_hue < rows[0]["held_loss_metal"]


def test_follow_decides_the_rim_once_its_core_is_metal():
    tex = np.full((18, 18, 3), [0.08, 0.06, 0.02], np.float32)   # the thread's core
    tex[:, 6:12] = [0.25, 0.12, 0.02]                            # its rim, another colour cluster
    tex[:, 12:] = [0.05, 0.06, 0.18]                             # the cloth
    bright = tex.copy()
    bright[:, :12] = [0.9, 0.7, 0.3]

    def model():
        m = GuidedMaps(tex, size=18, gain_grid=2, clusters=3, init_roughness=0.3, init_metallic=0.3)
        core, rim = int(m.members[:, 0, 0].argmax()), int(m.members[:, 0, 8].argmax())
        m.use_metal_colour(rate=3.0, allowed=np.isin(np.arange(3), [core, rim]))
        with torch.no_grad():
            m.metal_logit[rim] = np.log(0.01 / 0.99) / float(m.metal_scale[rim])   # the fit left it dielectric
        return m, core, rim

    for follow in (False, True):
        m, core, rim = model()
        rows = decide_metals(m, _env(), 1.0, _loss_to(bright), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10,
                             follow=follow)
        assert [r["cluster"] for r in rows] == ([core, rim] if follow else [core])
        assert all(r["decision"] == "metal" for r in rows)
    m, core, rim = model()   # the core stays as fitted: nothing follows
    rows = decide_metals(m, _env(), 1.0, _loss_to(tex), 12, epochs=20, lr=0.05, lr_env=0.05, ramp=10, follow=True)
    assert [(r["cluster"], r["decision"]) for r in rows] == [(core, "as fitted")]


def test_metal_decide_validates_and_the_profiles_decide():
    from saft.appearance.config import cpu_profile

    AppearanceConfig(metal_colour=True, metal_decide=30).validate()
    AppearanceConfig(metal_colour=True, metal_decide=40, metal_decide_ramp=20).validate()
    AppearanceConfig(metal_colour=True, metal_decide=40, metal_decide_glossy=0.5).validate()
    assert AppearanceConfig().metal_decide_glossy == 0.0 and cpu_profile().metal_decide_glossy == 0.5
    for bad in (dict(metal_decide=-1), dict(metal_decide_ramp=-1), dict(metal_decide_glossy=-0.1),
                dict(metal_decide_glossy=1.5)):
        with pytest.raises(Exception):
            AppearanceConfig(**bad).validate()
    p = cpu_profile()
    assert (p.metal_decide, p.metal_decide_ramp, p.metal_decide_follow) == (40, 20, True)


def test_the_fit_decides_its_half_metal_clusters_and_records_it():
    """End to end on a tiny scene: every cluster has a metal colour (no gate) and starts half metal, so
    each is decided; appearance.json's materials carry the decision and its held-out losses."""
    from saft.appearance.config import cpu_profile
    from saft.appearance.fit import fit_appearance
    from saft.appearance.params import linear_to_srgb
    from saft.synthetic.appearance import make_scene

    sc = make_scene(n_frames=2, image_size=32, map_size=32, render_spp=16)
    cfg = cpu_profile()
    cfg.epochs, cfg.frames_per_epoch, cfg.texel_size, cfg.image_scale, cfg.clusters = 2, 1, 64, 1.0, 2
    cfg.metal_gate, cfg.init_metallic, cfg.metal_decide, cfg.texture_frames, cfg.normal_grid = 0.0, 0.5, 2, 0, 0
    res = fit_appearance(sc.vertices, sc.triangles, sc.uvs, sc.camera, sc.rgb, sc.mask, cfg,
                         init_texture=linear_to_srgb(torch.as_tensor(sc.diffuse)).numpy())
    decided = [m["metal_decision"] for m in res.materials if "metal_decision" in m]
    assert decided and all(d["decision"] in ("metal", "as fitted") for d in decided)
    assert all(np.isfinite([d["held_loss_metal"], d["held_loss_dielectric"], d["held_loss_fitted"]]).all()
               for d in decided)
    for m in res.materials:
        if m.get("metal_decision", {}).get("decision") == "metal" and m["determined"]:
            assert m["metallic"] == pytest.approx(1.0, abs=1e-6)
