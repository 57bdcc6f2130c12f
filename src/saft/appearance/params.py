"""Trainable appearance parameters: the texture decoder (or plain per-texel maps) and the environment map.

Maps are returned as a dict of torch tensors, row 0 = TOP of the texture image:
``diffuse`` (S, S, 3) linear albedo in (0, 1), ``roughness`` (S, S) >= min_roughness, ``metallic`` (S, S).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as Fnn
from torch import nn


def logit(p: float) -> float:
    """log(p / (1 − p)) of p clamped to [1e-4, 1 − 1e-4]: a sigmoid parameter's start."""
    p = min(max(p, 1e-4), 1 - 1e-4)
    return math.log(p / (1 - p))


def _split_maps(logits: torch.Tensor, min_roughness: float) -> dict[str, torch.Tensor]:
    """(5, S, S) logits → dict of maps (sigmoid; roughness clamped >= min_roughness)."""
    x = torch.sigmoid(logits)
    return {
        "diffuse": x[0:3].permute(1, 2, 0),
        "roughness": x[3].clamp_min(min_roughness),
        "metallic": x[4],
    }


def tiled_size(tiles_per_side: int, tile_size: int, overlap: int) -> int:
    """Output side of `tiles_per_side`² tiles of `tile_size` placed `tile_size - overlap` apart, with
    overlap/2 cropped at the borders: 4 tiles of 128 with 10 px overlap → 4·118 = 472."""
    return tiles_per_side * (tile_size - overlap)


def blend_tiles(tiles: torch.Tensor, overlap: int) -> torch.Tensor:
    """Blend (g*g, C, T, T) tiles on a g×g grid (row-major) with linear ramps over `overlap` pixels.

    Adjacent tiles share `overlap` pixels; weights ramp linearly across the shared band so the result is
    seamless; overlap//2 pixels are then cropped at each border so every output pixel is a full blend.
    """
    n, c, t, _ = tiles.shape
    g = int(round(math.sqrt(n)))
    assert g * g == n, "number of tiles must be a square"
    stride = t - overlap
    full = stride * (g - 1) + t
    ramp = torch.ones(t, dtype=tiles.dtype, device=tiles.device)
    if overlap > 0:
        r = (torch.arange(overlap, dtype=tiles.dtype, device=tiles.device) + 0.5) / overlap
        ramp[:overlap] = r
        ramp[-overlap:] = r.flip(0)
    w2 = ramp[:, None] * ramp[None, :]
    acc = tiles.new_zeros(c, full, full)
    wsum = tiles.new_zeros(1, full, full)
    for k in range(n):
        i, j = divmod(k, g)
        ys, xs = i * stride, j * stride
        acc[:, ys:ys + t, xs:xs + t] = acc[:, ys:ys + t, xs:xs + t] + tiles[k] * w2
        wsum[:, ys:ys + t, xs:xs + t] = wsum[:, ys:ys + t, xs:xs + t] + w2
    out = acc / wsum.clamp_min(1e-8)
    lo = overlap // 2
    hi = lo + tiled_size(g, t, overlap)
    return out[:, lo:hi, lo:hi]


class TextureDecoder(nn.Module):
    """The paper's map generator: a fixed random latent (latent_channels×4×4) → transposed convolutions →
    `num_tiles` tiles of tile_size² with 5 channels, blended with `overlap` pixels into one S×S set of maps
    (S = sqrt(num_tiles)·(tile_size − overlap): 472 for 16 tiles of 128 with 10 px).

    Trained from scratch (no pre-training, as in the paper). The last layer starts near zero with biases at
    the logits of the initial values, so the first maps are ~uniform grey (init_* values).
    """

    def __init__(self, tile_size: int = 128, num_tiles: int = 16, overlap: int = 10, latent_channels: int = 512,
                 min_roughness: float = 1e-3, init_diffuse: float = 0.5, init_roughness: float = 0.5,
                 init_metallic: float = 0.5, seed: int = 0):
        super().__init__()
        ups = int(round(math.log2(tile_size / 4)))
        if 4 * 2 ** ups != tile_size:
            raise ValueError("tile_size must be 4·2^k")
        self.tile_size, self.num_tiles, self.overlap = tile_size, num_tiles, overlap
        self.min_roughness = min_roughness
        gen = torch.Generator().manual_seed(seed)
        self.register_buffer("latent", torch.randn(1, latent_channels, 4, 4, generator=gen))
        layers: list[nn.Module] = []
        ch = latent_channels
        for k in range(ups):
            out = max(32, latent_channels // 2 ** (k + 1))
            layers += [nn.ConvTranspose2d(ch, out, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
            ch = out
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(ch, 5 * num_tiles, 3, padding=1)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            for m in self.body:
                if isinstance(m, nn.ConvTranspose2d):
                    nn.init.kaiming_normal_(m.weight, a=0.2)
                    nn.init.zeros_(m.bias)
            nn.init.normal_(self.head.weight, std=1e-3)
        bias = torch.tensor([logit(init_diffuse)] * 3 + [logit(init_roughness), logit(init_metallic)])
        with torch.no_grad():
            self.head.bias.copy_(bias.repeat(num_tiles))

    @property
    def size(self) -> int:
        return tiled_size(int(round(math.sqrt(self.num_tiles))), self.tile_size, self.overlap)

    def forward(self, env: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The maps (env: unused; every map model takes the env map, appearance.irradiance needs it)."""
        h = self.head(self.body(self.latent))  # (1, 5·n, T, T)
        tiles = h.reshape(self.num_tiles, 5, self.tile_size, self.tile_size)
        return _split_maps(blend_tiles(tiles, self.overlap), self.min_roughness)


class TexelMaps(nn.Module):
    """Plain per-texel maps (sigmoid of free logits), the alternative to the decoder."""

    def __init__(self, size: int = 472, min_roughness: float = 1e-3, init_diffuse: float = 0.5,
                 init_roughness: float = 0.5, init_metallic: float = 0.5):
        super().__init__()
        self.min_roughness = min_roughness
        init = torch.tensor([logit(init_diffuse)] * 3 + [logit(init_roughness), logit(init_metallic)])
        self.logits = nn.Parameter(init[:, None, None].repeat(1, size, size).clone())

    @property
    def size(self) -> int:
        return int(self.logits.shape[-1])

    def forward(self, env: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        return _split_maps(self.logits, self.min_roughness)


class EnvironmentMap(nn.Module):
    """Lat-long environment map (H×W×3 linear radiance), initialised to `init`, clamped >= `min_value`
    (call :meth:`clamp_` after every optimizer step). :meth:`forward` applies the colour schedule weight."""

    def __init__(self, height: int = 256, width: int = 512, init: float = 0.5, min_value: float = 0.01):
        super().__init__()
        self.min_value = min_value
        self.data = nn.Parameter(torch.full((height, width, 3), float(init)))

    @torch.no_grad()
    def clamp_(self) -> None:
        self.data.clamp_(min=self.min_value)

    def forward(self, colour_weight: float = 1.0) -> torch.Tensor:
        """(1 − w)·grey + w·colour, grey = the channel mean (w = 0: no hue at all)."""
        env = self.data.clamp_min(self.min_value)
        return with_colour_weight(env, colour_weight)


class PyramidEnvironmentMap(nn.Module):
    """Lat-long environment map as the exponential of a Laplacian-style pyramid of log-radiance grids:
    env = exp(Σ_l up(P_l)), P_l of (height, width) / 2^(levels-1-l), bilinearly upsampled (the azimuth
    wraps around). The coarse levels pool the sparse 1-spp gradients of many texels, so the map is fitted
    coarse to fine without a schedule; the log keeps it positive over a sun's dynamic range. Same
    interface as EnvironmentMap (forward(colour_weight), clamp_ is a no-op)."""

    def __init__(self, height: int = 32, width: int = 64, levels: int = 4, init: float = 0.5, min_value: float = 0.01):
        super().__init__()
        self.height, self.width, self.min_value = height, width, min_value
        shapes = [(max(1, height >> (levels - 1 - i)), max(2, width >> (levels - 1 - i))) for i in range(levels)]
        self.levels = nn.ParameterList([nn.Parameter(torch.zeros(1, 3, h, w)) for h, w in shapes])
        with torch.no_grad():
            self.levels[0].fill_(math.log(max(init, min_value)))

    @torch.no_grad()
    def clamp_(self) -> None:
        pass

    def log_radiance(self) -> torch.Tensor:
        out = 0.0
        for p in self.levels:
            if p.shape[-2:] == (self.height, self.width):
                out = out + p
                continue
            padded = torch.cat([p[..., -1:], p, p[..., :1]], dim=-1)  # wrap the azimuth before upsampling
            w = p.shape[-1]
            up = Fnn.interpolate(padded, scale_factor=(self.height / p.shape[-2], self.width / w), mode="bilinear",
                                 align_corners=False)
            pad = (up.shape[-1] - self.width) // 2
            out = out + up[..., pad:pad + self.width]
        return out[0].permute(1, 2, 0)

    def forward(self, colour_weight: float = 1.0) -> torch.Tensor:
        env = torch.exp(self.log_radiance()).clamp_min(self.min_value)
        return with_colour_weight(env, colour_weight)


def with_colour_weight(env: torch.Tensor, colour_weight: float) -> torch.Tensor:
    """(1 − w)·grey + w·env, grey = the channel mean (w = 0: no hue at all)."""
    if colour_weight >= 1.0:
        return env
    grey = env.mean(dim=2, keepdim=True).expand_as(env)
    if colour_weight <= 0.0:
        return grey
    return (1.0 - colour_weight) * grey + colour_weight * env


def colour_weight(epoch: int, total_epochs: int, grey_fraction: float = 0.4, blend_fraction: float = 0.2) -> float:
    """The grey → blend → colour schedule (paper: 800 grey, 400 blend, 800 colour of 2000 epochs).

    Returns 0 during the first grey_fraction·total epochs, then rises linearly to 1 over
    blend_fraction·total epochs, then stays 1.
    """
    grey = int(round(grey_fraction * total_epochs))
    blend = int(round(blend_fraction * total_epochs))
    if epoch < grey:
        return 0.0
    if blend <= 0 or epoch >= grey + blend:
        return 1.0
    return float(epoch - grey) / float(blend)


def env_amplitude(env: torch.Tensor) -> torch.Tensor:
    """L1 amplitude regulariser: mean |T_E|."""
    return env.abs().mean()


def env_smoothness(env: torch.Tensor) -> torch.Tensor:
    """Finite-difference smoothness FD(T_E): mean |∂x| + mean |∂y| (the azimuth wraps around)."""
    dx = env - torch.roll(env, shifts=1, dims=1)
    dy = env[1:] - env[:-1]
    return dx.abs().mean() + dy.abs().mean()


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer function (differentiable, input clamped to [0, 1])."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)


def srgb_to_linear(x):
    """Inverse sRGB transfer function (numpy or torch)."""
    if isinstance(x, torch.Tensor):
        return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)
    import numpy as np

    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)
