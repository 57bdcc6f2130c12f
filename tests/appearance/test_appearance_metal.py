"""A metal colour per cluster (appearance.metal) and the gate on the highlights' colour (appearance.metal_gate)."""

import numpy as np
import pytest
import torch

from saft.appearance.config import AppearanceConfig
from saft.appearance.evidence import cluster_evidence
from saft.appearance.guided import GuidedMaps
from saft.appearance.metal import METAL_F0_MIN, MetalColour, metal_blend
from saft.appearance.metal_gate import highlight_colour, highlight_hue


def _two_colour_texture(size=32):
    tex = np.full((size, size, 3), [0.08, 0.06, 0.02], np.float32)   # dark gold (a metal's frame-0 diffuse)
    tex[:, size // 2:] = [0.05, 0.06, 0.18]                         # dark blue cloth
    return tex


def test_metal_colours_are_bright_and_keep_the_clusters_hue():
    mc = MetalColour(np.array([[0.08, 0.06, 0.02], [0.01, 0.01, 0.01]]))
    c = mc.colours().detach()
    assert c.max(dim=1).values.tolist() == pytest.approx([0.8, 0.8], abs=1e-5)   # METAL_START
    assert c[0, 0] > c[0, 1] > c[0, 2]                                          # gold's order of channels
    with torch.no_grad():
        mc.bright_logit.fill_(-30.0)
    assert mc.colours().max(dim=1).values.min().item() == pytest.approx(METAL_F0_MIN, abs=1e-5)   # never darker


def test_metal_blend_is_zero_for_dielectric_and_metal():
    area = torch.tensor([0.5, 0.5])
    assert metal_blend(area, torch.tensor([0.0, 1.0])).item() == 0.0
    assert metal_blend(area, torch.tensor([0.5, 0.0])).item() == pytest.approx(0.125)


def test_default_model_is_unchanged_and_the_metal_colour_mixes_in():
    model = GuidedMaps(_two_colour_texture(), size=32, gain_grid=2, clusters=2, init_metallic=0.5)
    plain = model()
    assert torch.equal(plain["diffuse"], model.base_maps()["diffuse"])
    l1 = model.metal_prior(0.01, 0.5)
    assert l1.item() == pytest.approx(0.01 * model.metallic_l1().item(), rel=1e-6)   # no colour: the L1 prior
    gold = int(model.members[:, 0, 0].argmax())
    model.use_metal_colour(rate=3.0, allowed=np.arange(2) == gold)
    assert model.cluster_values()["metallic"].tolist() == pytest.approx([0.5, 0.5], abs=1e-6)   # same start
    maps = model()
    d0 = model.base_maps()["diffuse"]
    expect = 0.5 * d0[0, 0] + 0.5 * model.metal.colours()[gold]
    assert torch.allclose(maps["diffuse"][0, 0], expect, atol=1e-6)           # the gold cluster: mixed
    assert torch.equal(maps["diffuse"][0, -1], d0[0, -1])                      # the other: its texture
    # the allowed cluster gets the metal-or-not prior, the other the sparsity prior
    prior = model.metal_prior(0.01, 0.5)
    area = model.area
    assert prior.item() == pytest.approx(0.01 * 0.5 * area[1 - gold].item() + 0.5 * 0.25 * area[gold].item(), rel=1e-5)
    # the allowed cluster's metallic moves rate times as fast under the same optimiser step
    opt = torch.optim.Adam(model.parameters(), lr=0.1)
    model.cluster_values()["metallic"].sum().backward()
    opt.step()
    logits = (model.metal_logit * model.metal_scale).detach()
    assert logits[gold].item() == pytest.approx(-0.3, abs=1e-3) and logits[1 - gold].item() == pytest.approx(-0.1, abs=1e-3)


def test_evidence_mixes_the_metal_colour_for_the_metallic_it_tries():
    """The matte alternative renders the cluster with its dielectric diffuse (no metal colour)."""
    model = GuidedMaps(_two_colour_texture(), size=32, gain_grid=2, clusters=2, init_roughness=0.3, init_metallic=0.9)
    model.use_metal_colour()
    seen = []

    def render(f, d, r, m, e, spp, seed):
        seen.append(d.detach().clone())
        return d.mean(dim=(0, 1))

    cluster_evidence(model, torch.zeros(2, 4, 3), render, [0], lambda f, img: img.sum(), threshold=0.0)
    base = model.base_maps()["diffuse"]
    k0 = model.members[0] > 0
    assert not torch.allclose(seen[0][k0], base[k0])   # the fitted material: metal colour mixed in
    assert torch.allclose(seen[1][k0], base[k0])       # cluster 0 made matte: its own texture


def _frames(spec_colour, base, n=8, g=8):
    """n frames of a g×g one-cluster patch of colour `base`, a highlight of `spec_colour` on a different
    texel row in each frame, and a Lambertian brightening of every texel by up to 20 %."""
    rad = np.tile(np.asarray(base, np.float64), (n, g, g, 1))
    for f in range(n):
        rad[f] *= 1 + 0.2 * f / n
        rad[f, f % g] += 0.6 * np.asarray(spec_colour)
    return rad, np.ones((n, g, g), bool), np.zeros((g, g), int)


def test_highlight_colour_tells_a_metals_highlight_from_a_dielectrics():
    gold = [0.95, 0.70, 0.30]
    metal = highlight_colour(*_frames(np.array(gold) * 0.5, np.array(gold) * 0.1), k=1)
    red_satin = highlight_colour(*_frames([0.3, 0.3, 0.3], [0.5, 0.08, 0.12]), k=1)
    assert metal[0] > 0.9 and red_satin[0] < 0.3
    grey = highlight_colour(*_frames([0.3, 0.3, 0.3], [0.4, 0.4, 0.4]), k=1)
    assert np.isnan(grey[0])   # a grey cluster: its highlight's colour tells nothing
    rad, seen, labels = _frames([0.3, 0.3, 0.3], [0.5, 0.08, 0.12])
    rad[:] = rad[0]   # no motion, no highlight that comes and goes
    rad[:, 0] = [0.5, 0.08, 0.12]
    assert np.isnan(highlight_colour(rad, seen, labels, k=1)[0])
    rad, seen, labels = _frames(np.array(gold) * 0.5, np.array(gold) * 0.1)
    rad[:, :, :, :] = np.where(rad.max(-1, keepdims=True) > 0.2, 1.0, rad)   # every highlight clipped white
    assert np.isnan(highlight_colour(rad, seen, labels, k=1)[0])              # not taken for a white one


def test_highlight_hue_is_the_colour_of_a_metals_highlight():
    gold = np.array([0.95, 0.70, 0.30])
    hue = highlight_hue(*_frames(gold * 0.5, gold * 0.1), k=1)
    assert hue[0] == pytest.approx(gold / 0.95, abs=0.03)   # the F0's colour over its brightest channel
    satin = highlight_hue(*_frames([0.3, 0.3, 0.3], [0.5, 0.08, 0.12]), k=1)
    assert satin[0].min() > 0.6   # a dielectric's highlight: the light's colour (grey), not the cloth's red
    rad, seen, labels = _frames(gold * 0.5, gold * 0.1)
    rad[:] = rad[0]   # no highlight comes and goes
    rad[:, 0] = gold * 0.1
    assert np.isnan(highlight_hue(rad, seen, labels, k=1)[0]).all()


def test_set_hue_gives_a_cluster_this_colour_and_keeps_its_brightness():
    metal = MetalColour(np.array([[0.2, 0.2, 0.2], [0.05, 0.06, 0.18]]))
    before = metal.colours().detach().clone()
    metal.set_hue(0, [0.95, 0.70, 0.30])
    after = metal.colours().detach()
    assert after[0].max() == pytest.approx(before[0].max(), abs=1e-6)
    assert (after[0] / after[0].max()).numpy() == pytest.approx([1.0, 0.70 / 0.95, 0.30 / 0.95], abs=0.01)
    assert torch.equal(after[1], before[1])


def test_metal_options_validate():
    AppearanceConfig(metal_colour=True, metal_gate=0.5).validate()
    with pytest.raises(Exception):
        AppearanceConfig(metal_rate=0).validate()
    with pytest.raises(Exception):
        AppearanceConfig(metal_gate=1.5).validate()
