"""The frame-0 irradiance of appearance.irradiance: the texel normals (the UV rasterisation is
appearance.detail's, tested there), the env map's direction convention and the cosine integral, checked
against Mitsuba's own rendering of a white patch."""

import math

import numpy as np
import pytest
import torch

from saft.appearance.irradiance import (FrameZeroIrradiance, IrradianceMaps, env_direction, irradiance_matrix,
                                        texel_normals)
from saft.scene.camera import look_at


def _grid(n=5, lo=0.1, hi=0.8):
    """An n×n vertex grid mesh in the plane z = 0 and its UVs on [lo, hi]² (the rest of the UV square empty),
    one triangle left out (a hole)."""
    s = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(s, s)
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], -1)
    uvs = lo + (hi - lo) * verts[:, :2]
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            tris += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return verts, np.array(tris[:-1]), uvs


def test_texel_normals_face_the_camera_and_fill_the_empty_texels():
    verts, tris, uvs = _grid()
    verts[:, 2] = 0.5 * verts[:, 0]    # a tilted plane: normal ∝ (−0.5, 0, 1) by the winding
    n_true = np.array([-0.5, 0.0, 1.0]) / math.hypot(0.5, 1.0)
    for eye, sign in (((0.5, 0.5, 3.0), 1.0), ((0.5, 0.5, -3.0), -1.0)):
        n = texel_normals(verts, tris, uvs, eye, 32)
        assert np.abs(n - sign * n_true).max() < 1e-6   # every texel, the empty ones from their neighbours


def test_uniform_light_gives_pi_times_radiance_for_any_normal():
    rng = np.random.default_rng(0)
    normals = rng.standard_normal((50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    m = irradiance_matrix(normals, 16, 32)
    assert torch.allclose(m.sum(1), torch.full((50,), math.pi), rtol=2e-3)
    # and a light from one half of the sky only: the normals facing it receive more
    env = np.ones((16, 32, 3), np.float32)
    env[9:] = 0.0    # rows below the horizon (θ > 90°) dark
    e = (m @ torch.as_tensor(env).reshape(-1, 3))[:, 0].numpy()
    assert np.corrcoef(e, normals[:, 1])[0, 1] > 0.95


def _blob_env(direction, height=32, width=64):
    theta = np.arange(height) * math.pi / (height - 1)
    u = (np.arange(width) + 0.5) / width
    c = env_direction(theta[:, None], u[None, :]) @ (np.asarray(direction) / np.linalg.norm(direction))
    e = 0.2 + 20.0 * np.exp(40.0 * (c - 1.0))
    return np.stack([e, 0.8 * e, 0.6 * e + 0.1], -1).astype(np.float32)


@pytest.mark.parametrize("normal", [(0, 0, -1), (0, 0.7, -0.7), (-0.5, 0.2, -0.84), (0.0, -0.5, -0.87)])
def test_irradiance_matches_mitsubas_white_patch(normal):
    """π·radiance / albedo of a flat patch (roughness 1, metallic 0) rendered by ClothRenderer under an env map
    with a bright blob equals E0 from irradiance_matrix within 8 %. The principled BSDF's diffuse is
    Burley's, not Lambert's: measured here (1024 spp) it is 0.93–1.07 × Lambert (above 1 where the light
    comes from far off the normal, below where it comes near the normal at an oblique view); the
    specular lobe (F0 = 0.04) is taken out by rendering the same patch black. A wrong direction
    convention (the azimuth turned by half, the poles swapped) is off by more than 25 % in red (the blob's
    strongest channel) for these normals."""
    from saft.appearance.renderer import ClothRenderer

    blob = np.array([0.3, 0.8, -0.5])
    env = _blob_env(blob)
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    verts = 0.1 * np.stack([-t - b, t - b, t + b, -t + b])   # (v1 − v0) × (v2 − v0) ∝ t × b = n
    tris, uvs = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    K = np.array([[200.0, 0, 31.5], [0, 200.0, 31.5], [0, 0, 1]])
    cam = look_at(np.array([0, 0, -1.0]), np.zeros(3), np.array([0, -1.0, 0]), K, 64, 64)
    r = ClothRenderer(tris, uvs, cam, max_depth=2, map_shape=(4, 4), env_shape=env.shape[:2])
    r.set_vertices(verts)
    rough, metal = np.ones((4, 4)), np.zeros((4, 4))
    white = r.render_numpy(np.full((4, 4, 3), 1.0), rough, metal, env, spp=1024)
    black = r.render_numpy(np.zeros((4, 4, 3)), rough, metal, env, spp=1024)
    mask = white.max(-1) > 0
    measured = math.pi * (white - black)[mask].mean(0)
    e0 = (irradiance_matrix(n[None], *env.shape[:2]) @ torch.as_tensor(env).reshape(-1, 3))[0].numpy()
    assert np.all(np.abs(measured / e0 - 1) < 0.08), (measured, e0)
    # the azimuth turned by half; the poles swapped (a horizontal normal cannot tell up from down)
    for flip in [[-1, 1, -1]] + ([[1, -1, 1]] if abs(n[1]) > 0.3 else []):
        wrong = (irradiance_matrix(n[None] * flip, *env.shape[:2]) @ torch.as_tensor(env).reshape(-1, 3))[0, 0]
        assert abs(measured[0] / float(wrong) - 1) > 0.25   # the test tells these conventions apart


def test_irradiance_maps_divide_the_shading_out_and_pass_gradients_to_the_env():
    verts, tris, uvs = _grid(9, 0.0, 1.0)
    verts[:, 2] = 0.3 * np.sin(3 * verts[:, 0])     # a fold: the shading varies across the cloth
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    cam = look_at(np.array([0.5, 0.5, 3.0]), np.array([0.5, 0.5, 0.0]), np.array([0, -1.0, 0]), K, 64, 64)
    env = torch.as_tensor(_blob_env([0.2, 0.5, 0.8], 16, 32))
    e0 = FrameZeroIrradiance(verts, np.array(tris), uvs, cam, grid=32, env_shape=(16, 32))
    albedo = np.zeros((32, 32, 3), np.float32)
    albedo[:] = [0.6, 0.4, 0.2]
    texture = albedo * e0(env).numpy() / math.pi       # the frame-0 radiance of a Lambertian cloth
    model = IrradianceMaps(texture / texture.max(), e0, size=32, gain_grid=4, clusters=1)
    with torch.no_grad():
        model.gain.fill_(math.log(texture.max()))    # the texture's normalisation, as one grey gain
    env_leaf = env.clone().requires_grad_(True)
    diffuse = model(env_leaf)["diffuse"]
    # the fold's shading is gone; the edge texels interpolate E0 from fewer covered neighbours
    assert torch.allclose(diffuse[2:-2, 2:-2], torch.as_tensor(albedo)[2:-2, 2:-2], rtol=0.03)
    assert texture[..., 0].std() / texture[..., 0].mean() > 0.1   # while the texture varied
    diffuse.sum().backward()
    g = env_leaf.grad
    assert g is not None and (g <= 0).all() and (g < 0).float().mean() > 0.4   # more light: a darker albedo
    with pytest.raises(ValueError, match="env map"):
        model()



def test_irradiance_maps_start_from_the_physical_division():
    """Under the uniform env map L the fit starts from, E0 = π·L everywhere (a flat cloth), so the first
    diffuse is T / L, clipped at 1 (the start that was measured: BENCHMARKS "A physically divided diffuse,
    adopted"; starting from T itself made the cotton glossier)."""
    verts, tris, uvs = _grid(5, 0.0, 1.0)
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    cam = look_at(np.array([0.5, 0.5, 3.0]), np.array([0.5, 0.5, 0.0]), np.array([0, -1.0, 0]), K, 64, 64)
    e0 = FrameZeroIrradiance(verts, np.array(tris), uvs, cam, grid=8, env_shape=(8, 16))
    texture = np.linspace(0.1, 0.9, 32 * 32 * 3, dtype=np.float32).reshape(32, 32, 3)
    for level in (0.5, 2.0):
        model = IrradianceMaps(texture, e0, size=32, gain_grid=4, clusters=1)
        diffuse = model(torch.full((8, 16, 3), level))["diffuse"]
        expected = (model.detailed_texture() / level).clamp(0, 1)
        assert torch.allclose(diffuse, expected, rtol=3e-3, atol=1e-5)
