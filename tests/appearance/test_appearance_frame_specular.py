"""appearance.frame_specular: frame 0's specular in the texture, measured from the frames' median."""

import math

import numpy as np
import torch

from saft.appearance.frame_specular import FrameStack, frame_specular, sh9_basis, sh9_irradiance_projection
from saft.appearance.irradiance import FrameZeroIrradiance, IrradianceMaps, env_direction, irradiance_matrix
from saft.scene.camera import look_at


def _blob_env(direction, height=16, width=32, sharp=8.0):
    theta = np.arange(height) * math.pi / (height - 1)
    u = (np.arange(width) + 0.5) / width
    c = env_direction(theta[:, None], u[None, :]) @ (np.asarray(direction) / np.linalg.norm(direction))
    e = 0.3 + 5.0 * np.exp(sharp * (c - 1.0))
    return np.stack([e, 0.8 * e, 0.6 * e + 0.1], -1).astype(np.float32)


def _normals(n, seed=0):
    v = np.random.default_rng(seed).standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_sh9_irradiance_matches_the_exact_cosine_integral():
    normals = _normals(200)
    p = torch.as_tensor(sh9_irradiance_projection(16, 32), dtype=torch.float32)
    uniform = torch.full((16, 32, 3), 0.7)
    e = torch.as_tensor(sh9_basis(normals), dtype=torch.float32) @ (p @ uniform.reshape(-1, 3))
    assert torch.allclose(e, torch.full_like(e, 0.7 * math.pi), rtol=2e-3)
    env = torch.as_tensor(_blob_env([0.3, 0.8, -0.5]))
    exact = (irradiance_matrix(normals, 16, 32) @ env.reshape(-1, 3)).numpy()
    approx = (torch.as_tensor(sh9_basis(normals), dtype=torch.float32) @ (p @ env.reshape(-1, 3))).numpy()
    rel = approx / exact
    assert np.abs(np.median(rel) - 1) < 0.02 and np.abs(rel - 1).max() < 0.1
    # the direction matters: the same light from the opposite side is far off
    flipped = (torch.as_tensor(sh9_basis(-normals), dtype=torch.float32) @ (p @ env.reshape(-1, 3))).numpy()
    assert np.abs(flipped / exact - 1).max() > 0.5


def _stack(frames=9, grid=16, seed=1):
    """A FrameStack built by hand: every texel's normal changes from frame to frame, the radiance is a
    Lambertian cloth's (albedo · E_f / π, 2 % noise) under a blob env map."""
    rng = np.random.default_rng(seed)
    env = torch.as_tensor(_blob_env([0.2, 0.9, 0.3]))
    stack = FrameStack.__new__(FrameStack)
    base = np.array([0.0, 0.6, 0.8])
    normals = base + 0.35 * rng.standard_normal((frames, grid, grid, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    stack.frames = list(range(frames))
    stack.basis = torch.as_tensor(sh9_basis(normals), dtype=torch.float32)
    stack.projection = torch.as_tensor(sh9_irradiance_projection(16, 32), dtype=torch.float32)
    stack.seen = torch.ones(frames, grid, grid, dtype=torch.bool)
    albedo = np.where((np.arange(grid)[:, None] // 4 + np.arange(grid)[None] // 4)[..., None] % 2, [0.7, 0.3, 0.2],
                      [0.2, 0.4, 0.6])
    lambert = albedo * stack.irradiance(env).numpy() / math.pi
    stack.radiance = torch.as_tensor(lambert * (1 + 0.02 * rng.standard_normal(lambert.shape)), dtype=torch.float32)
    return stack, env, lambert


def test_a_moving_highlight_is_measured_where_frame_0_has_it_and_nowhere_else():
    stack, env, lambert = _stack()
    highlight = np.zeros((9, 16, 16, 3), np.float32)
    for f in range(9):                    # a streak that moves one column per frame
        highlight[f, :, 3 + f] = 0.5
    stack.radiance += torch.as_tensor(highlight)
    s0, d0 = frame_specular(stack, env)
    # the streak of frame 0, measured (less the significance margin: 3 robust deviations of the 2 % noise)
    assert np.abs(s0[:, 3] - 0.5).max() < 0.15 and abs(s0[:, 3].mean() - 0.5) < 0.05
    assert s0[:, 4:].max() < 0.03 and s0[:, :3].max() < 0.03         # nothing where frame 0 had none
    assert np.abs(d0[:, 3] / lambert[0, :, 3] - 1).max() < 0.1     # D0: frame 0 without the streak


def test_no_highlight_measures_nothing():
    stack, env, _ = _stack()
    i0 = stack.radiance[0].numpy()
    s0, _ = frame_specular(stack, env)
    # the model's 2 % noise is not specular: at most a few per cent of a few texels (per channel)
    assert s0.sum() < 1e-3 * i0.sum() and (s0 / i0).max() < 0.05
    unthresholded, _ = frame_specular(stack, env, significance=0.0)
    assert unthresholded.sum() > 5 * s0.sum()                         # which the significance takes out
    # a texel that frame 0 does not see is left alone
    stack.radiance[0, 2, 2] += 1.0
    stack.seen[0, 2, 2] = False
    assert frame_specular(stack, env)[0][2, 2].max() == 0.0


def _square_and_camera(n=5):
    """The unit square in z = 0 as an n×n vertex grid (UVs = x, y) and a 64×64 camera 3 above its centre."""
    s = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(s, s)
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], -1)
    tris = np.array([[i * n + j, i * n + j + 1, i * n + j + n + 1] for i in range(n - 1) for j in range(n - 1)]
                    + [[i * n + j, i * n + j + n + 1, i * n + j + n] for i in range(n - 1) for j in range(n - 1)])
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
    cam = look_at(np.array([0.5, 0.5, 3.0]), np.array([0.5, 0.5, 0.0]), np.array([0, -1.0, 0]), K, 64, 64)
    return verts, tris, cam


def test_frame_stack_samples_each_frame_through_its_mesh():
    verts, tris, cam = _square_and_camera()
    rgb = np.zeros((2, 64, 64, 3), np.float32)
    rgb[0, :, 32:] = 0.5                       # frame 0: grey on the image's right half (the cloth's u < 0.5)
    rgb[1] = 0.5                               # frame 1: grey, black on the image's 20 leftmost columns
    rgb[1, :, :20] = 0.0
    moved = verts + [0.1, 0.0, 0.0]            # frame 1's cloth moved by 0.1 (3.3 pixels to the left)
    stack = FrameStack(np.stack([verts, moved]), tris, verts[:, :2], cam, rgb, np.ones((2, 64, 64)), 16, (8, 16))
    lin = ((0.5 + 0.055) / 1.055) ** 2.4
    assert stack.seen.all() and np.allclose(stack.basis[..., 2].numpy(), 0.488603, atol=1e-5)  # facing +z
    r0, r1 = stack.radiance[0, ..., 0].numpy(), stack.radiance[1, ..., 0].numpy()
    assert np.allclose(r0[:, :8], lin, atol=1e-3) and np.allclose(r0[:, 8:], 0.0, atol=1e-3)
    # pixel column 20 is x = 0.845 on frame 0's cloth, x = 0.745 on frame 1's: texel columns 12-15 (u > 0.75)
    assert np.allclose(r1[:, :12], lin, atol=1e-3) and np.allclose(r1[:, 12:], 0.0, atol=1e-3)


def test_irradiance_maps_take_frame_0s_specular_off_the_texture_with_a_floor():
    verts, tris, cam = _square_and_camera()
    e0 = FrameZeroIrradiance(verts, tris, verts[:, :2], cam, grid=8, env_shape=(8, 16))
    model = IrradianceMaps(np.full((16, 16, 3), 0.4, np.float32), e0, size=16, gain_grid=2, clusters=1)
    env = torch.full((8, 16, 3), 0.5)
    before = model(env)["diffuse"]
    spec = np.zeros((4, 4, 3), np.float32)
    spec[:, :2] = 0.1                       # the left half: a highlight of a quarter of the texture
    spec[:, 3] = 5.0                        # the right column: an overestimate, floored at a tenth of T
    model.set_specular0(spec)
    after = model(env)["diffuse"]
    assert torch.allclose(after[:, :6], before[:, :6] * 0.75, rtol=1e-4)
    assert torch.allclose(after[:, -2:], before[:, -2:] * 0.1, rtol=1e-4)
    assert model.state_dict().keys() == IrradianceMaps(np.full((16, 16, 3), 0.4, np.float32), e0, size=16,
                                                      gain_grid=2, clusters=1).state_dict().keys()

