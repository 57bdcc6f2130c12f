"""An image loss that tolerates a highlight a few pixels off (appearance.loss_blur).

On saft's own motion the meshes are a centimetre off, so a sharp highlight lands a few pixels from where
the mesh puts it; the per-pixel loss then prefers a rough, dim highlight that covers both places. This
loss adds the same linearised sRGB residual after a Gaussian blur: a highlight that is only misplaced
costs little there, while one of the wrong strength or spread still costs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as Fnn


def gaussian_kernel(sigma: float) -> torch.Tensor:
    """The 1-D normalised Gaussian of this σ (pixels), radius 3σ."""
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def blur_image(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W, C) blurred by a separable Gaussian of σ pixels (zero outside the image)."""
    k = gaussian_kernel(sigma).to(img)
    r = k.numel() // 2
    x = img.permute(2, 0, 1)[:, None]                                   # C, 1, H, W
    x = Fnn.conv2d(x, k.view(1, 1, 1, -1), padding=(0, r))
    x = Fnn.conv2d(x, k.view(1, 1, -1, 1), padding=(r, 0))
    return x[:, 0].permute(1, 2, 0)


def blurred_linearised_mse(pred_linear: torch.Tensor, target_linear: torch.Tensor, slope: torch.Tensor,
                           mask: torch.Tensor, sigma: float) -> torch.Tensor:
    """mean (G_σ * (m · sRGB'(t)·(x − t)))² over the mask's pixels: fit.masked_linearised_srgb_mse of the
    residual blurred by a Gaussian of σ pixels (the primal and adjoint samples stay decorrelated, so its
    1-spp gradient stays unbiased)."""
    w = mask[..., None]
    res = blur_image(slope * (pred_linear - target_linear) * w, sigma)
    return (res ** 2).sum() / (w.sum() * 3.0).clamp_min(1e-8)
