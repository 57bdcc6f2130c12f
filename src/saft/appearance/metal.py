"""A metal colour per material cluster (``appearance.metal_colour``, issue 28: the lamé's gold threads).

In the metallic-roughness model a metal's base colour is its normal-incidence reflectance F0, and no metal
is dark: the dimmest common metals have a brightest F0 channel (linear) of about 0.55 (titanium, chromium,
iron), gold (1.000, 0.766, 0.336), silver (0.972, 0.960, 0.915). The guided diffuse is the phase-1 texture
divided by its frame-0 shading, an albedo for a Lambertian cloth but not a metal's F0 (a metal's frame-0
radiance is its specular reflection, which the division takes for a dark diffuse). So each cluster k gets
a colour of its own,

    c_k = s_k · h_k / max(h_k),   s_k = METAL_F0_MIN + (1 − METAL_F0_MIN) · sigmoid(a_k),   h_k = sigmoid(η_k),

bright (brightest channel in [METAL_F0_MIN, 1]) with a free hue, and the renderer's base colour is
(1 − m) · diffuse + m · c (m the cluster's metallic): a dielectric keeps the texture's colour, a metal
reflects its own. ``metal_blend`` (Σ_k area_k · m_k (1 − m_k)) prices a half metal, whose metal colour
would otherwise be a free colour of its diffuse lobe, and is 0 for a dielectric and a metal alike.

appearance.metal_gate (optional) decides before the fit which clusters get a metal colour at all.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from saft.appearance.params import logit

METAL_F0_MIN = 0.5        # the smallest brightest channel of a metal's F0 (linear; titanium 0.54, iron 0.58)
METAL_START = 0.8         # the brightness every cluster's metal colour starts at


def start_hue(mean_colour: np.ndarray) -> np.ndarray:
    """(K, 3) hue logits from the clusters' mean texture colours (linear): each colour over its brightest
    channel, scaled into (0.02, 0.9) so that no channel starts where the sigmoid is flat."""
    c = np.maximum(np.asarray(mean_colour, dtype=np.float64), 1e-6)
    h = np.clip(0.9 * c / c.max(axis=-1, keepdims=True), 0.02, 0.9)
    return np.log(h / (1 - h))


class MetalColour(nn.Module):
    """K bright metal colours (module docstring). mean_colour (K, 3): the clusters' mean texture colours
    (linear), the hues' start; allowed (K,) bool: the clusters that may be metal (others keep metallic 0)."""

    def __init__(self, mean_colour: np.ndarray, allowed: np.ndarray | None = None):
        super().__init__()
        k = len(mean_colour)
        start = (METAL_START - METAL_F0_MIN) / (1 - METAL_F0_MIN)
        self.bright_logit = nn.Parameter(torch.full((k,), logit(start)))
        self.hue_logit = nn.Parameter(torch.as_tensor(start_hue(mean_colour), dtype=torch.float32))
        allowed = np.ones(k, bool) if allowed is None else np.asarray(allowed, bool)
        self.register_buffer("allowed", torch.as_tensor(allowed.astype(np.float32)))

    @torch.no_grad()
    def set_hue(self, k: int, colour) -> None:
        """Cluster k's hue to this colour's (linear RGB, any brightness; start_hue's scaling), its
        brightness kept."""
        self.hue_logit[k] = torch.as_tensor(start_hue(np.asarray(colour, np.float64)[None])[0], dtype=self.hue_logit.dtype)

    def colours(self) -> torch.Tensor:
        """(K, 3) linear metal colours, brightest channel in [METAL_F0_MIN, 1]."""
        hue = torch.sigmoid(self.hue_logit)
        bright = METAL_F0_MIN + (1 - METAL_F0_MIN) * torch.sigmoid(self.bright_logit)
        return bright[:, None] * hue / hue.max(dim=1, keepdim=True).values

    def mix(self, diffuse: torch.Tensor, metallic: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        """(S, S, 3) base colour (1 − m)·diffuse + m·c for diffuse (S, S, 3), metallic (S, S), members
        (K, S, S) the clusters' one-hot masks."""
        colour = torch.einsum("kc,khw->hwc", self.colours(), members)
        m = metallic[..., None]
        return (1 - m) * diffuse + m * colour


def metal_blend(area: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """Σ_k area_k · m_k · (1 − m_k): zero for a dielectric and for a metal, largest for a half metal."""
    return (area * metallic * (1 - metallic)).sum()
