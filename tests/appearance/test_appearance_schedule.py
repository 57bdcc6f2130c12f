"""Environment-map colour schedule, regularisers and the texture decoder's shape/initialisation."""

import pytest
import torch

from saft.appearance.config import AppearanceConfig, cpu_profile, profile_for_device
from saft.appearance.params import (EnvironmentMap, TexelMaps, TextureDecoder, blend_tiles, colour_weight,
                                    env_amplitude, env_smoothness, linear_to_srgb, srgb_to_linear)


def test_schedule_paper_numbers():
    n = 2000
    assert colour_weight(0, n) == 0.0 and colour_weight(799, n) == 0.0
    assert colour_weight(800, n) == 0.0
    assert colour_weight(1000, n) == pytest.approx(0.5)
    assert colour_weight(1199, n) == pytest.approx(399 / 400)
    assert colour_weight(1200, n) == 1.0 and colour_weight(1999, n) == 1.0


def test_schedule_scales_with_epochs():
    n = 100
    assert colour_weight(39, n) == 0.0
    assert colour_weight(50, n) == pytest.approx(0.5)
    assert colour_weight(60, n) == 1.0


def test_grey_phase_has_no_hue():
    env = EnvironmentMap(8, 16)
    with torch.no_grad():
        env.data.copy_(torch.rand(8, 16, 3) + 0.1)
    grey = env(0.0)
    assert torch.allclose(grey[..., 0], grey[..., 1]) and torch.allclose(grey[..., 1], grey[..., 2])
    assert torch.allclose(grey.mean(), env.data.mean(), atol=1e-6)  # brightness kept
    half = env(0.5)
    assert torch.allclose(half, 0.5 * grey + 0.5 * env.data)
    assert torch.equal(env(1.0), env.data)
    # gradients in the grey phase reach every channel equally (only brightness can change)
    g = torch.zeros(8, 16, 3)
    g[..., 0] = 1.0
    env.data.grad = None
    env(0.0).backward(g)
    assert torch.allclose(env.data.grad[..., 0], env.data.grad[..., 2])


def test_env_clamp_and_regularisers():
    env = EnvironmentMap(4, 8, init=0.5, min_value=0.01)
    with torch.no_grad():
        env.data[0, 0, 0] = -1.0
    env.clamp_()
    assert env.data.min() >= 0.01
    flat = torch.full((4, 8, 3), 0.3)
    assert env_smoothness(flat) == 0.0
    assert env_amplitude(flat) == pytest.approx(0.3)


def test_decoder_paper_size_and_grey_init():
    dec = TextureDecoder()  # paper: 16 tiles of 128 with 10 px overlap, latent 512x4x4
    assert dec.size == 472 and tuple(dec.latent.shape) == (1, 512, 4, 4)
    with torch.no_grad():
        maps = dec()
    assert maps["diffuse"].shape == (472, 472, 3)
    assert maps["roughness"].shape == (472, 472) and maps["metallic"].shape == (472, 472)
    for m in maps.values():
        assert abs(float(m.mean()) - 0.5) < 0.02 and float(m.std()) < 0.02


def test_decoder_min_roughness_and_texels():
    dec = TextureDecoder(tile_size=16, overlap=2, latent_channels=32, init_roughness=1e-6)
    with torch.no_grad():
        assert float(dec()["roughness"].min()) >= 1e-3
    tex = TexelMaps(size=24)
    assert tex()["diffuse"].shape == (24, 24, 3)


def test_blend_tiles_is_seamless_for_constant_tiles():
    tiles = torch.full((16, 2, 12, 12), 0.7)
    out = blend_tiles(tiles, 4)
    assert out.shape == (2, 4 * 8, 4 * 8)
    assert torch.allclose(out, torch.tensor(0.7))


def test_srgb_roundtrip():
    x = torch.linspace(0, 1, 101)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-5)


def test_config_profiles():
    paper = AppearanceConfig()
    assert paper.epochs == 2000 and paper.lr_decoder == 2e-4 and paper.betas_decoder == (0.99, 0.9999)
    assert paper.lr_env == 1e-2 and paper.spp == 1 and paper.env_height == 256 and paper.env_width == 512
    assert paper.lambda_env_l1 == 1e-5 and paper.lambda_env_smooth == 5e-5
    cpu = profile_for_device("cpu")
    assert cpu.profile == "cpu" and cpu.epochs < paper.epochs
    cuda = profile_for_device("cuda")
    assert cuda.profile == "cuda" and cuda.epochs == paper.epochs and cuda.frames_per_epoch == 0
    assert cuda.image_scale == 1.0 and cuda.spp == paper.spp and cuda.maps == cpu.maps == "guided"
    assert (cuda.env_output_height, cuda.env_output_width) == (paper.env_output_height, paper.env_output_width)
    assert profile_for_device(torch.device("cpu")).profile == "cpu"
    assert AppearanceConfig.from_dict(cpu.to_dict()) == cpu
    cpu.validate()
    bad = cpu_profile()
    bad.maps = "nope"
    with pytest.raises(Exception):
        bad.validate()
