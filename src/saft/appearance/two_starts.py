"""Two starts, Occam's choice: fit phase 3 from the profile's roughness and from a matte one, keep the matte
result unless the glossier one explains the frames clearly better (issue 28).

Why: with the phase-1 texture as diffuse and a free diffuse gain, a rough and a glossy material explain a
matte cloth's video almost equally well (cotton: 6 % apart), so the fitted roughness ends near where it
starts (BENCHMARKS.md, issue 28 "Second round"). A glossy start keeps rough fabrics glossy; a matte start
never finds a satin's highlight. Fitting both and preferring the matte answer unless the data insists is
the same principle as the metallic sparsity prior and the per-cluster evidence test (appearance.evidence).

The comparison loss is unbiased for the renderer's noise: every frame is rendered twice with independent
seeds and the loss is the mean of the PRODUCT of the two residuals (E[(x1 − t)(x2 − t)] = (E[x] − t)²), and
both fits are rendered with the same seeds, so their difference is not a difference of noise levels (a
glossy material renders noisier, which the plain squared error would count against it).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

HELD_OUT_SPP = 16          # per render; two renders per frame (product of residuals)
HELD_OUT_SEEDS = (104729, 130363)  # shared by both fits, distinct from the fit's and the evidence test's seeds


@torch.no_grad()
def held_out_loss(render: Callable, frames: list[int], pair_loss: Callable, spp: int = HELD_OUT_SPP) -> list[float]:
    """Per frame, the noise-free image loss of the final maps: pair_loss(frame, render(f, s1), render(f, s2)).

    render(frame, spp, seed) → linear image of the fitted maps; pair_loss(frame, a, b) → the weighted mean
    of (a − t)(b − t) (see product_loss).
    """
    s1, s2 = HELD_OUT_SEEDS
    return [float(pair_loss(f, render(f, spp, s1 * 7 + f), render(f, spp, s2 * 7 + f))) for f in frames]


def product_loss(a: torch.Tensor, b: torch.Tensor, target: torch.Tensor, slope: torch.Tensor,
                 mask: torch.Tensor) -> torch.Tensor:
    """The linearised sRGB loss (fit.masked_linearised_srgb_mse) with its square replaced by the product of
    two independent renders' residuals: the Monte Carlo variance term drops out (unbiased, may be < 0)."""
    prod = slope ** 2 * (a - target) * (b - target)
    w = mask[..., None]
    return (prod * w).sum() / (w.sum() * 3.0).clamp_min(1e-8)


def choose(glossy_loss: float, matte_loss: float, margin: float) -> str:
    """'glossy' only if the glossier fit's loss is lower than the matter fit's by more than `margin`
    (relative to the matter fit's loss); otherwise 'matte' (the data does not insist)."""
    return "glossy" if glossy_loss < (1.0 - margin) * matte_loss else "matte"


def mean_roughness(result) -> float:
    return float(np.mean(result.roughness))


def pick(profile_result, matte_result, margin: float) -> tuple[object, dict]:
    """Of two fitted AppearanceResults (each with .held_out_loss per frame), the one `choose` keeps, and the
    record written to appearance.json (which start won, both losses, both mean roughnesses)."""
    fits = {"profile_start": profile_result, "matte_start": matte_result}
    loss = {k: float(np.mean(r.held_out_loss)) for k, r in fits.items()}
    rough = {k: mean_roughness(r) for k, r in fits.items()}
    glossy, matte = sorted(fits, key=lambda k: rough[k])   # the glossier (lower mean roughness) first
    winner = glossy if choose(loss[glossy], loss[matte], margin) == "glossy" else matte
    record = {"winner": winner, "margin": margin, "held_out_loss": loss, "mean_roughness": rough,
              "init_roughness": {k: float(r.config.init_roughness) for k, r in fits.items()},
              "cpu_seconds": {k: float(r.cpu_seconds) for k, r in fits.items()}}
    return fits[winner], record
