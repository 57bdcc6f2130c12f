"""Two starts, chosen on held-out frames: fit phase 3 from the profile's roughness and from a matte one on
most of the frames, keep the one that predicts the frames left out of both fits (issue 28).

Why: with the phase-1 texture as diffuse and a free diffuse gain, a rough and a glossy material explain a
matte cloth's fitted frames almost equally well (cotton: 6–8 % apart), so the fitted roughness ends near
where it starts (BENCHMARKS.md, issue 28 "Second round"). A glossy start keeps rough fabrics glossy; a matte
start never finds a satin's highlight. On frames that neither fit saw, a highlight moves with the view and
the normal: a truly glossy surface predicts where it goes, a gain that was bent to fit the seen frames does
not. The glossier fit is kept only if it predicts the held-out frames better in a paired test across those
frames (its per-frame loss differences' mean above ``z`` standard errors: no margin set on any fabric);
if neither start is better beyond that noise, the data does not determine the roughness, and the result
says so (``start_choice["determined"]``, the note of ``undetermined_note``).

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


def split_frames(n_frames: int, every: int, mode: str = "interleaved") -> tuple[np.ndarray, np.ndarray]:
    """(fit frames, held-out frames), n_frames // every held out: "interleaved", every `every`-th frame from
    the middle of the first group (32 frames, every 4: 2, 6, …, 30); "last", the last ones (24, …, 31: poses
    further from any fitted one). Too few frames to spare (< 2·every): nothing is held out and the frames
    are scored in-sample."""
    frames = np.arange(n_frames)
    if every < 2 or n_frames < 2 * every:
        return frames, frames
    held = frames[every // 2::every] if mode == "interleaved" else frames[n_frames - n_frames // every:]
    return np.setdiff1d(frames, held), held


@torch.no_grad()
def pair_losses(render: Callable, frames, pair_loss: Callable, spp: int = HELD_OUT_SPP) -> list[float]:
    """Per frame, the noise-free image loss of the final maps: pair_loss(frame, render(f, s1), render(f, s2)).

    render(frame, spp, seed) → linear image of the fitted maps; pair_loss(frame, a, b) → the weighted mean
    of (a − t)(b − t) (see product_loss).
    """
    s1, s2 = HELD_OUT_SEEDS
    return [float(pair_loss(int(f), render(int(f), spp, s1 * 7 + int(f)), render(int(f), spp, s2 * 7 + int(f))))
            for f in frames]


def product_loss(a: torch.Tensor, b: torch.Tensor, target: torch.Tensor, slope: torch.Tensor,
                 mask: torch.Tensor) -> torch.Tensor:
    """The linearised sRGB loss (fit.masked_linearised_srgb_mse) with its square replaced by the product of
    two independent renders' residuals: the Monte Carlo variance term drops out (unbiased, may be < 0)."""
    prod = slope ** 2 * (a - target) * (b - target)
    w = mask[..., None]
    return (prod * w).sum() / (w.sum() * 3.0).clamp_min(1e-8)


def paired_z(glossy: list[float], matte: list[float]) -> float:
    """How many standard errors the glossier fit's per-frame loss lies below the matter fit's (paired over
    the same frames; > 0: the glossier predicts better). One frame: ±inf by the sign of the difference."""
    d = np.asarray(matte, np.float64) - np.asarray(glossy, np.float64)
    if d.size < 2:
        return float(np.sign(d.sum()) * np.inf) if d.size else 0.0
    se = d.std(ddof=1) / np.sqrt(d.size)
    return float(d.mean() / se) if se > 0 else float(np.sign(d.mean()) * np.inf)


def pick(profile_result, matte_result, z: float) -> tuple[object, dict]:
    """Of two fitted AppearanceResults (each with .held_out_loss per held-out frame), the one whose mean
    held-out loss is lower, and the record written to appearance.json; "determined" is False when neither
    beats the other by more than `z` paired standard errors (then the roughness is not told by the data)."""
    fits = {"profile_start": profile_result, "matte_start": matte_result}
    rough = {k: float(np.mean(r.roughness)) for k, r in fits.items()}
    glossy, matte = sorted(fits, key=lambda k: rough[k])   # the glossier (lower mean roughness) first
    score = paired_z(fits[glossy].held_out_loss, fits[matte].held_out_loss)
    winner = glossy if score > 0 else matte
    record = {"winner": winner, "z": z, "paired_z_glossier_better": score, "determined": bool(abs(score) > z),
              "held_out_loss": {k: float(np.mean(r.held_out_loss)) for k, r in fits.items()},
              "held_out_loss_per_frame": {k: list(r.held_out_loss) for k, r in fits.items()},
              "fitted_frames_loss": {k: float(np.mean(r.fitted_loss)) for k, r in fits.items()
                                     if getattr(r, "fitted_loss", None)},
              "mean_roughness": rough,
              "init_roughness": {k: float(r.config.init_roughness) for k, r in fits.items()},
              "cpu_seconds": {k: float(r.cpu_seconds) for k, r in fits.items()}}
    return fits[winner], record


def undetermined_roughness_note(record: dict) -> str | None:
    """A sentence for appearance.json when the held-out frames could not tell a glossy from a matte fit."""
    if record is None or record.get("determined", True):
        return None
    return (f"roughness is not determined by the data: the fits from a glossy and from a matte start predict the "
            f"held-out frames equally well (paired z {record['paired_z_glossier_better']:.2f}, within "
            f"±{record['z']:g}); the one kept ({record['winner']}) was the better by less than the noise")
