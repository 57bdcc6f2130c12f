"""Known material maps of fabric kinds, and known environment maps: the appearance benchmark's ground truth.

``fabric_maps(kind, size)`` → (base colour (S, S, 3) linear, roughness (S, S), metallic (S, S)), float32,
row 0 = TOP of the texture image (v = 1), for a principled metallic-roughness BSDF:

* ``cotton``:  plain matte cotton, one colour with a faint weave; roughness 0.85–0.95, no metal;
* ``print``:   a printed pattern (dots and leaves) on cotton; the ink a little glossier (0.6) than the
               cloth (0.85); no metal;
* ``plaid``:   a woven tartan (thread colours in warp and weft), roughness 0.7 ± the weave; no metal;
* ``satin``:   a low-roughness satin (0.22) with a woven jacquard motif at 0.4; no metal;
* ``lame``:    dark cloth (roughness 0.8) with gold metallic warp threads (metallic 0.95, roughness 0.3).

Materials follow the threads (a thread of one colour has one material), as in real fabrics.

``environment_map(kind, height, width)`` → (H, W, 3) linear radiance in Mitsuba's lat-long convention (row 0
looks along world +y; column u along (-sin φ, ·, cos φ), φ = (2u - 1)π, as ``benchmark_scenes.sky_with_sun``):

* ``video``:  a blue sky over a warm ground with a sun above, left and in front of the cloth;
* ``unseen``: an indoor light: a warm softbox to the right, a cool fill light below-left, a dim grey room;
  never shown to the fit, for relighting.
"""

from __future__ import annotations

import numpy as np

from saft.appearance.irradiance import env_direction

FABRICS = {
    "cotton": "plain matte cotton",
    "print": "printed pattern on cotton, glossier ink",
    "plaid": "woven tartan",
    "satin": "low-roughness satin with a jacquard motif",
    "lame": "dark cloth with gold metallic threads",
}
ENVIRONMENTS = ("video", "unseen")


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """u (columns) and v (rows, 0 at the top) in [0, 1) at texel centres."""
    t = (np.arange(size) + 0.5) / size
    return np.meshgrid(t, t)


def _weave(size: int, period: int = 8) -> np.ndarray:
    """A faint basket weave in [-1, 1] (the over/under of warp and weft every `period` texels)."""
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    return np.where(((i // (period // 2)) + (j // (period // 2))) % 2 == 0, 1.0, -1.0)


def _stripes(t: np.ndarray, bands: list[tuple[float, float, int]]) -> np.ndarray:
    """Index of the band of a repeating sett: bands (start, end, colour index) in [0, 1) of one repeat."""
    out = np.zeros(t.shape, dtype=np.int64)
    for lo, hi, c in bands:
        out[(t >= lo) & (t < hi)] = c
    return out


def fabric_maps(kind: str, size: int = 512, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(base colour, roughness, metallic) of a fabric kind (see the module docstring)."""
    if kind not in FABRICS:
        raise ValueError(f"unknown fabric {kind!r} (one of {', '.join(FABRICS)})")
    rng = np.random.default_rng(seed)
    u, v = _grid(size)
    weave = _weave(size)
    grain = rng.standard_normal((size, size)) * 0.01
    metal = np.zeros((size, size))
    if kind == "cotton":
        base = np.array([0.55, 0.30, 0.12]) * (1 + 0.05 * weave + grain)[..., None]
        rough = 0.9 + 0.05 * weave
    elif kind == "print":
        ground = np.array([0.70, 0.66, 0.55])
        cx, cy = (u * 5) % 1 - 0.5, (v * 5) % 1 - 0.5
        dots = cx ** 2 + cy ** 2 < 0.09
        leaves = np.abs(np.sin(2 * np.pi * (3 * u + 2 * v)) * np.cos(2 * np.pi * (2 * u - 3 * v))) > 0.75
        base = np.broadcast_to(ground, (size, size, 3)).copy()
        base[leaves] = [0.10, 0.35, 0.12]
        base[dots] = [0.55, 0.06, 0.08]
        ink = dots | leaves
        base = base * (1 + 0.03 * weave + grain)[..., None]
        rough = np.where(ink, 0.6, 0.85) + 0.03 * weave
    elif kind == "plaid":
        colours = np.array([[0.08, 0.10, 0.35], [0.45, 0.04, 0.05], [0.06, 0.25, 0.08], [0.75, 0.65, 0.20]])
        sett = [(0.0, 0.4, 0), (0.4, 0.7, 1), (0.7, 0.9, 2), (0.9, 0.96, 3), (0.96, 1.0, 0)]
        warp = colours[_stripes((u * 3) % 1, sett)]
        weft = colours[_stripes((v * 3) % 1, sett)]
        over = (weave > 0)[..., None]  # which thread lies on top at this texel
        base = np.where(over, warp, weft) * (1 + grain)[..., None]
        rough = 0.7 + 0.06 * weave
    elif kind == "satin":
        motif = np.cos(2 * np.pi * 4 * u) * np.cos(2 * np.pi * 4 * v) > 0.55
        base = np.where(motif[..., None], [0.50, 0.08, 0.12], [0.42, 0.05, 0.09]) * (1 + grain)[..., None]
        rough = np.where(motif, 0.4, 0.22)
    else:  # lame: gold metallic warp threads, 3/16 of every 1/8 of the width (19 % of the area)
        period = max(size // 8, 8)
        j = np.arange(size)[None, :].repeat(size, 0)
        thread = (j % period) < (3 * period) // 16
        base = np.where(thread[..., None], [0.95, 0.70, 0.30], [0.05, 0.06, 0.18]) * (1 + grain)[..., None]
        rough = np.where(thread, 0.3, 0.8)
        metal = np.where(thread, 0.95, 0.0)
    base = np.clip(base, 0.01, 0.99)
    return (base.astype(np.float32), np.clip(rough, 0.02, 1.0).astype(np.float32),
            np.clip(metal, 0.0, 1.0).astype(np.float32))


def _directions(height: int, width: int) -> np.ndarray:
    """(H, W, 3) world directions of the pixel centres (Mitsuba's lat-long convention: env_direction)."""
    th = (np.arange(height) + 0.5) / height * np.pi
    return env_direction(th[:, None], ((np.arange(width) + 0.5) / width)[None, :])


def _lobe(d: np.ndarray, direction, colour, sharpness: float) -> np.ndarray:
    s = np.asarray(direction, dtype=np.float64)
    s = s / np.linalg.norm(s)
    return np.asarray(colour, dtype=np.float64) * np.exp(sharpness * ((d @ s)[..., None] - 1))


def environment_map(kind: str, height: int = 64, width: int = 128) -> np.ndarray:
    """A known lat-long environment map (see the module docstring); the camera of the appearance scenes
    looks along -z from z > 0, so 'in front of the cloth' is +z."""
    d = _directions(height, width)
    up = d[..., 1:2]
    if kind == "video":
        env = 0.08 + np.array([0.10, 0.16, 0.32]) * np.clip(up, 0, 1) + np.array([0.12, 0.09, 0.05]) * np.clip(-up, 0, 1)
        env = env + _lobe(d, (-0.45, 0.65, 0.62), (80.0, 72.0, 60.0), 400.0)
    elif kind == "unseen":
        env = 0.05 + np.array([0.06, 0.06, 0.06]) * np.clip(up, 0, 1)
        env = env + _lobe(d, (0.7, 0.3, 0.65), (3.0, 2.2, 1.4), 25.0) + _lobe(d, (-0.6, -0.35, 0.7), (0.5, 0.8, 1.4), 10.0)
    else:
        raise ValueError(f"unknown environment {kind!r} (one of {', '.join(ENVIRONMENTS)})")
    return env.astype(np.float32)
