"""A physically divided diffuse (``appearance.diffuse_shading = "irradiance"``, issue 28).

The phase-1 texture T is the frame-0 radiance of the cloth (linear), so for a Lambertian cloth
T(u) ≈ albedo(u) · E0(u) / π, with E0(u) the irradiance at texel u under the env map from the frame-0
normal at u. Instead of a free colour gain (``GuidedMaps``, whose colour trades with the env map's and
makes rough fabrics glossy) the diffuse is

    diffuse = clamp(π · T_d(u) / E0↑(u) · exp(g↑), 0, 1),

T_d the guided texture (in-cluster blur plus its learnt detail share), E0 computed from the env map being
fitted (so the light's colour leaves the diffuse as the env map takes it), g a GREY coarse log-gain grid for
what irradiance without visibility or interreflection misses. (A per-channel global gain on top brought the
cotton's gloss back, no gain at all lost the plaid and the satin: BENCHMARKS "A physically divided diffuse".)

E0 = Σ_env pixels L_p · ∫ w_p(ω) max(0, n·ω) dω: w_p are the bilinear weights of Mitsuba's ``envmap``
lookup (row i at θ = π·i/(H−1) from world +Y, column j at u = (j + ½)/W with u = atan2(x, −z)/2π,
periodic in u; checked against the emitter in tests/appearance/test_appearance_irradiance.py). The
(texels × env pixels) matrix of those integrals is computed once by quadrature on a grid `oversample`
times finer than the env map, so E0 is one matmul per epoch, differentiable w.r.t. the env map.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as Fnn
from scipy.ndimage import distance_transform_edt
from torch import nn

from saft.appearance.detail import texel_triangles
from saft.appearance.guided import GuidedMaps
from saft.scene.camera import Camera
from saft.scene.mesh import vertex_normals


def fill_nearest(values: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """values (S, S, C) with every texel outside `covered` (S, S) set to its nearest covered texel's."""
    if covered.all() or not covered.any():
        return values
    _, (ii, jj) = distance_transform_edt(~covered, return_indices=True)
    return values[ii, jj]


def texel_normals(vertices, triangles, uvs, camera_centre, size: int) -> np.ndarray:
    """(size, size, 3) unit surface normals per texel at the given geometry: the vertex normals
    interpolated barycentrically, turned to face `camera_centre` (the cloth's BSDF is two-sided: a texel
    seen from its back is lit on its back), texels outside the UV layout from their nearest covered one."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    tri_id, bary = texel_triangles(t, uvs, size)
    covered = tri_id >= 0
    corners = t[np.maximum(tri_id, 0)]                              # (S, S, 3) vertex ids
    n = (bary[..., None] * vertex_normals(v, t)[corners]).sum(-2)
    p = (bary[..., None] * v[corners]).sum(-2)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    facing = ((np.asarray(camera_centre, dtype=np.float64) - p) * n).sum(-1)
    n = np.where(facing[..., None] < 0, -n, n)
    n[~covered] = 0.0
    return fill_nearest(n, covered)


def env_direction(theta, u):
    """World direction (…, 3) of the env map's lat-long coordinates (θ from +Y, u = atan2(x, −z)/2π)."""
    theta, u = np.broadcast_arrays(np.asarray(theta, dtype=np.float64), np.asarray(u, dtype=np.float64))
    s = np.sin(theta)
    return np.stack([s * np.sin(2 * math.pi * u), np.cos(theta), -s * np.cos(2 * math.pi * u)], -1)


def linear_weights(x: np.ndarray, n: int, periodic: bool) -> np.ndarray:
    """(len(x), n): the linear-interpolation weights of samples at continuous pixel positions x."""
    x0 = np.floor(x).astype(np.int64)
    if not periodic:
        x0 = np.clip(x0, 0, n - 2)
    f = x - x0
    w = np.zeros((len(x), n))
    rows = np.arange(len(x))
    np.add.at(w, (rows, x0 % n), 1 - f)
    np.add.at(w, (rows, (x0 + 1) % n), f)
    return w


def env_quadrature(height: int, width: int, oversample: int = 2):
    """The midpoint rule over the sphere on oversample·(height − 1) × oversample·width cells of the lat-long
    map (module docstring: Mitsuba's lookup): the cells' directions (nt, nu, 3), the solid angle of a cell
    in each row (nt,), and the bilinear weights from the cells to the env map's rows (nt, H) and columns
    (nu, W)."""
    nt, nu = oversample * (height - 1), oversample * width
    theta = (np.arange(nt) + 0.5) * math.pi / nt
    u = (np.arange(nu) + 0.5) / nu
    return (env_direction(theta[:, None], u[None, :]), np.sin(theta) * (math.pi / nt) * (2 * math.pi / nu),
            linear_weights(theta / math.pi * (height - 1), height, False), linear_weights(u * width - 0.5, width, True))


def irradiance_matrix(normals: np.ndarray, height: int, width: int, oversample: int = 2,
                      chunk: int = 64) -> torch.Tensor:
    """(N, height·width) float32 M with E(n_k) = M[k] @ env.reshape(-1, 3) for unit normals (N, 3):
    ∫ w_p(ω) max(0, n·ω) dω by env_quadrature's midpoint rule."""
    d, row_omega, w_theta, w_u = env_quadrature(height, width, oversample)
    nt, nu = d.shape[:2]
    d_t = torch.as_tensor(d.reshape(-1, 3))                                  # (nt·nu, 3)
    dw = torch.as_tensor(np.repeat(row_omega, nu))
    w_theta, w_u = torch.as_tensor(w_theta), torch.as_tensor(w_u)           # (nt, H), (nu, W)
    n_t = torch.as_tensor(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    out = torch.empty(len(n_t), height * width, dtype=torch.float32)   # float64 only chunk by chunk
    for s in range(0, len(n_t), chunk):
        c = (n_t[s:s + chunk] @ d_t.T).clamp_min(0.0) * dw                   # (n, nt·nu)
        c = c.reshape(-1, nt, nu) @ w_u                                        # (n, nt, W)
        out[s:s + len(c)] = torch.einsum("nah,naw->nhw", w_theta.expand(len(c), -1, -1), c).reshape(len(c), -1)
    return out


# E0's texel grid: the shading varies at the mesh's scale (R1's 32×32 template: 2 texels per quad). Not
# measurable on the appearance benchmark, whose frame 0 is flat (16, 32 and 64 gave the same E0).
IRRADIANCE_GRID = 64
# what is left of T_d at least after frame 0's specular is taken off (IrradianceMaps.diffuse_texture)
SPECULAR_FLOOR = 0.1


class FrameZeroIrradiance(nn.Module):
    """E0 on a grid×grid texel grid of the UV square at the frame-0 geometry; forward(env (H, W, 3)) →
    (grid, grid, 3), differentiable in env. The env map's shape is fixed at construction."""

    def __init__(self, vertices0, triangles, uvs, camera: Camera, env_shape: tuple[int, int], grid: int = IRRADIANCE_GRID,
                 oversample: int = 2):
        super().__init__()
        self.grid = int(grid)
        normals = texel_normals(vertices0, triangles, uvs, camera.camera_to_world[:3, 3], self.grid)
        # not persistent: rebuilt from the geometry (at grid 64 and a 64×128 env map it is 134 MB)
        self.register_buffer("matrix", irradiance_matrix(normals.reshape(-1, 3), *env_shape, oversample),
                             persistent=False)

    def forward(self, env: torch.Tensor) -> torch.Tensor:
        return (self.matrix @ env.reshape(-1, 3)).reshape(self.grid, self.grid, 3)


class IrradianceMaps(GuidedMaps):
    """GuidedMaps whose diffuse is the texture divided by its frame-0 irradiance (module docstring); the
    gain is a grey g×g log-gain grid (`self.gain`, one channel). forward(env) needs the env map the
    renderer gets."""

    def __init__(self, texture_linear: np.ndarray, irradiance: FrameZeroIrradiance, **kw):
        super().__init__(texture_linear, **kw)
        g = int(self.gain.shape[-1])
        # g = 0: the first diffuse is π·T / E0 under the first env map (uniform L: T / L). Starting from T
        # itself instead (g = log L, the absolute scale GuidedMaps starts from) made the cotton glossier
        # (roughness MAE 0.060 -> 0.195, BENCHMARKS "A physically divided diffuse, adopted"); a cloth brighter
        # than L starts clipped at 1, which the env map's own gradient (the render is too dark) undoes
        self.gain = nn.Parameter(torch.zeros(1, 1, g, g))
        self.irradiance = irradiance
        # frame 0's specular in texture space (linear, on a coarse grid, upsampled), taken off T_d before the
        # division when the fit measures it (appearance.frame_specular); zero: nothing taken off
        self.register_buffer("specular0", torch.zeros(1, 3, 1, 1), persistent=False)
        self.has_specular0 = False  # decided on the host when set: no device sync per render (issue 27)

    def shading(self, env: torch.Tensor) -> torch.Tensor:
        """(S, S, 3) E0↑ / exp(g↑): what the texture is divided by (π aside)."""
        s = self.size
        e0 = self.irradiance(env).clamp_min(1e-6).permute(2, 0, 1)[None]
        e0 = Fnn.interpolate(e0, size=(s, s), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
        gain = Fnn.interpolate(self.gain, size=(s, s), mode="bilinear", align_corners=False)[0, 0][..., None]
        return e0 * torch.exp(-gain)

    @torch.no_grad()
    def set_specular0(self, specular: np.ndarray) -> None:
        """specular (G, G, 3) linear: frame 0's specular in texture space (appearance.frame_specular)."""
        specular = np.asarray(specular, dtype=np.float32)
        self.specular0 = torch.as_tensor(specular).permute(2, 0, 1)[None].to(self.specular0.device)
        self.has_specular0 = bool(specular.any())

    def diffuse_texture(self) -> torch.Tensor:
        """(S, S, 3) T_d less frame 0's specular, kept at least SPECULAR_FLOOR·T_d (an overestimated
        highlight leaves no black hole)."""
        t = self.detailed_texture()
        if not self.has_specular0:
            return t
        s = Fnn.interpolate(self.specular0, size=(self.size, self.size), mode="bilinear", align_corners=False)
        return torch.maximum(t - s[0].permute(1, 2, 0), SPECULAR_FLOOR * t)

    def base_maps(self, env: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        if env is None:
            raise ValueError("IrradianceMaps needs the env map: model(env)")
        diffuse = (math.pi * self.diffuse_texture() / self.shading(env)).clamp(0.0, 1.0)
        return {"diffuse": diffuse, **self.material_maps()}
