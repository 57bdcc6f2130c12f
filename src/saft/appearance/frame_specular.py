"""The frame-0 specular in the phase-1 texture, measured from the other frames (issue 28, a curved frame 0).

The phase-1 texture T is frame 0's radiance; ``diffuse_shading = "irradiance"`` divides it by the frame-0
irradiance E0. What T holds beyond albedo · E0 / π is mostly frame 0's specular: on a billowed satin the
sun's streak (BENCHMARKS "Appearance with a curved frame 0": 19 % of T on average, up to 122 %), which the
division then paints into the diffuse. Here that specular is estimated from the data, not from the fit's
own gloss: every frame f is sampled into texture space through its mesh (``detail.project_to_texture``)
and divided by its own irradiance E_f (the texel's normal in frame f under the env map being fitted). For a
Lambertian texel I_f / E_f = albedo / π in every frame; a highlight adds to the frames it passes through, and
a highlight that moves over the cloth does not reach the per-texel median over the frames. So

    D0(u) = E0(u) · median_f I_f(u) / E_f(u)      (frame 0 as the median would see it: specular-free)
    S0(u) = max(0, I0(u) − D0(u))                 (what frame 0 has beyond it)

is frame 0's moving specular; a broad specular that every frame shows (a rough, glossy cloth) stays in the
median and in T, where it keeps holding the fitted gloss down as before (taking all of the specular off T
freed the cotton's gloss: the oracle of the section above).

E_f needs the irradiance for many normals per epoch, so it uses the env map's order-2 spherical-harmonic
projection (Ramamoorthi and Hanrahan 2001: E(n) = Σ_lm Â_l L_lm Y_lm(n); within a few per cent of the exact
cosine integral for smooth light, see the tests) instead of irradiance.py's exact matrix.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from saft.appearance.detail import project_to_texture, texel_triangles
from saft.appearance.irradiance import env_quadrature, texel_normals
from saft.appearance.params import srgb_to_linear
from saft.scene.camera import Camera

# the texel grid of the frames (the cloth of the benchmark's 320x240 videos spans about 150 pixels: about
# two pixels per texel; the template is 16x16 quads: four texels per quad)
FRAME_GRID = 64
# the cosine lobe's SH coefficients per band l (Â_0, Â_1, Â_2)
_A = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)


def sh9_basis(directions) -> np.ndarray:
    """(…, 9) the real spherical harmonics of bands 0-2 at unit directions (…, 3) (world x, y, z)."""
    d = np.asarray(directions, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([np.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x,
                     1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3.0 * z * z - 1.0), 1.092548 * x * z,
                     0.546274 * (x * x - y * y)], -1)


def sh9_irradiance_projection(height: int, width: int, oversample: int = 2) -> np.ndarray:
    """(9, height·width) P with P @ env.reshape(-1, 3) = the irradiance coefficients Â_l · L_lm (9, 3) of a
    lat-long env map in Mitsuba's convention (appearance.irradiance.env_quadrature's midpoint rule and bilinear
    lookup), so that E(n) = sh9_basis(n) @ (P @ env)."""
    d, row_omega, w_theta, w_u = env_quadrature(height, width, oversample)
    y = sh9_basis(d) * row_omega[:, None, None]                                  # (nt, nu, 9)
    p = np.einsum("th,tuk,uw->khw", w_theta, y, w_u).reshape(9, -1)
    return p * np.repeat(_A, (1, 3, 5))[:, None]


class FrameStack:
    """The frames sampled into a grid×grid texel grid through their meshes, with each texel's normal per
    frame, for frame_specular(). vertices (F, V, 3) world, rgb_srgb (F, H, W, 3), mask (F, H, W); frame 0
    is always included. env_shape: the (H, W) of the env maps frame_specular() will get."""

    def __init__(self, vertices, triangles, uvs, camera: Camera, rgb_srgb, mask, grid: int,
                 env_shape: tuple[int, int], frames=None):
        frames = sorted(set(range(len(vertices)) if frames is None else frames) | {0})
        tri_of, bary = texel_triangles(triangles, uvs, grid)
        eye = camera.camera_to_world[:3, 3]
        radiance, seen, basis = [], [], []
        for f in frames:
            linear = srgb_to_linear(np.clip(np.asarray(rgb_srgb[f], dtype=np.float64), 0.0, 1.0))
            values, valid = project_to_texture(vertices[f], triangles, tri_of, bary, camera, linear, mask[f])
            radiance.append(values)
            seen.append(valid)
            basis.append(sh9_basis(texel_normals(vertices[f], triangles, uvs, eye, grid)))
        self.frames = frames
        self.radiance = torch.as_tensor(np.stack(radiance), dtype=torch.float32)   # (F, G, G, 3) linear
        self.seen = torch.as_tensor(np.stack(seen))                                # (F, G, G) bool
        self.basis = torch.as_tensor(np.stack(basis), dtype=torch.float32)         # (F, G, G, 9)
        self.projection = torch.as_tensor(sh9_irradiance_projection(*env_shape), dtype=torch.float32)

    def irradiance(self, env: torch.Tensor) -> torch.Tensor:
        """(F, G, G, 3) each frame's irradiance per texel under env (H, W, 3)."""
        coeffs = self.projection @ env.reshape(-1, 3).to(self.projection)          # (9, 3)
        return (self.basis @ coeffs).clamp_min(1e-6)


# S0 counts where frame 0 is an outlier among the texel's frames: beyond SIGNIFICANCE robust standard
# deviations (1.4826 × MAD over the frames) of log(I_f / E_f) in luminance above their median (the mismatch
# that the Lambertian, SH-lit model leaves: on the curved cotton and print, whose specular is broad and in
# every frame, frame 0 is within 3 of them at 99 % of the texels; the satin's streak at 14 % of them)
SIGNIFICANCE = 3.0
SPREAD_FLOOR = 0.01     # the least per-texel spread (log) assumed (a texel seen in few, equal frames)


@torch.no_grad()
def frame_specular(stack: FrameStack, env: torch.Tensor, min_seen: int = 3,
                   significance: float = SIGNIFICANCE) -> tuple[np.ndarray, np.ndarray]:
    """(S0 (G, G, 3), D0 (G, G, 3)) linear (module docstring): frame 0's specular beyond the median of the
    irradiance-normalised frames, S0 = max(0, I0 − D0·exp(significance·σ)), σ the texel's robust standard
    deviation over the frames (1.4826 × MAD of log(I_f / E_f) in luminance, at least SPREAD_FLOOR); and frame
    0's specular-free radiance D0. Texels that frame 0 does not see, or fewer than min_seen frames see, get
    S0 = 0 and D0 = I0."""
    e = stack.irradiance(env)
    nan = torch.tensor(float("nan"))
    ratio = torch.where(stack.seen[..., None], stack.radiance / e, nan).numpy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # texels no frame sees
        log_lum = np.log(np.maximum(np.nanmean(ratio, axis=-1), 1e-8))            # (F, G, G), NaN: not seen
        median = np.nanmedian(ratio, axis=0)                                       # (G, G, 3)
        spread = 1.4826 * np.nanmedian(np.abs(log_lum - np.nanmedian(log_lum, axis=0)), axis=0)
    counted = ((stack.seen.sum(0) >= min_seen) & stack.seen[0]).numpy()
    i0 = stack.radiance[0].numpy()
    d0 = np.where(counted[..., None], e[0].numpy() * np.nan_to_num(median), i0)
    margin = np.exp(significance * np.maximum(np.nan_to_num(spread), SPREAD_FLOOR))[..., None]
    return np.maximum(i0 - d0 * margin, 0.0).astype(np.float32), d0.astype(np.float32)

