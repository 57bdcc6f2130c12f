"""Metal or not, decided per cluster after the fit (``appearance.metal_decide``, issue 28: the lamé's threads).

The metal colour (appearance.metal) and the gate (appearance.metal_gate) let a cluster be metal, but whether
it ends metal is left to how far 150 epochs of noisy gradients carry its metallic: the lamé's gold threads
end at 0.08-0.24 on saft's own motion (a half metal whose diffuse explains most of the frames) and at 0.98
when found (BENCHMARKS "A metal colour per cluster…": "a question of travel, not of evidence"). A cloth's
thread is metal or it is not, so each metal-coloured cluster that ends between the two is refitted briefly
both ways from the fitted state, its metallic pinned at 1 (its metal colour) and at 0 (its texture), and
keeps the one whose image loss on frames the refits did not see is lower.
"""

from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch

PIN = 20.0   # |metallic logit| of a pinned cluster (sigmoid(±20): 1 and 0 to 2e-9)


def held_out_frames(n_frames: int, count: int = 8) -> tuple[list[int], list[int]]:
    """(train, held): `count` evenly spaced frames held out, the rest to refit on (all of them if none is left)."""
    held = sorted({int(f) for f in np.linspace(0, n_frames - 1, min(n_frames, count)).round()})
    train = [f for f in range(n_frames) if f not in held]
    return (train or held), held


def _pin(model, k: int, metal: bool) -> None:
    with torch.no_grad():
        model.metal_logit[k] = (PIN if metal else -PIN) / float(model.metal_scale[k])


def refit_pinned(model, env: torch.Tensor, frame_loss: Callable, train: list[int], k: int, metal: bool,
                 epochs: int, lr: float, batch: int = 3, seed: int = 0) -> None:
    """`epochs` Adam steps (rate lr) of every map parameter but the detail share (appearance.detail decides
    which frames may teach it) on `batch` random frames of `train` each, cluster k's metallic pinned at 1
    (metal) or 0; the env map and the shading normals stay as fitted.

    frame_loss(frame, maps, spp, seed) → scalar: the image loss of the maps rendered at that frame."""
    _pin(model, k, metal)
    params = [p for name, p in model.named_parameters() if name != "detail_logit"]
    opt = torch.optim.Adam(params, lr=lr)
    rng = np.random.default_rng(seed)
    for epoch in range(epochs):
        frames = rng.choice(train, min(batch, len(train)), replace=False)
        maps = model(env)
        leaves = {name: v.detach().requires_grad_(True) for name, v in maps.items()}
        for f in frames:
            (frame_loss(int(f), leaves, 1, 104_729 + epoch * 1000 + int(f)) / len(frames)).backward()
        opt.zero_grad(set_to_none=True)
        names = [n for n in leaves if leaves[n].grad is not None]
        torch.autograd.backward([maps[n] for n in names], [leaves[n].grad for n in names])
        for p in params:
            if p.grad is not None and not torch.isfinite(p.grad).all():
                p.grad = None   # a Monte Carlo outlier: skip it, as the fit does
        if model.metal_logit.grad is not None:
            model.metal_logit.grad[k] = 0.0
        opt.step()
        _pin(model, k, metal)


@torch.no_grad()
def held_out_loss(model, env: torch.Tensor, frame_loss: Callable, held: list[int], spp: int) -> float:
    """The image loss summed over the held-out frames, each rendered with a fixed seed (the same samples for
    every alternative, so that the Monte Carlo noise cancels in their difference)."""
    maps = model(env)
    return sum(float(frame_loss(f, maps, spp, 7919 + f)) for f in held)


def decide_metals(model, env: torch.Tensor, frame_loss: Callable, n_frames: int, epochs: int, lr: float,
                  spp: int = 4, seed: int = 0, low: float = 0.05, high: float = 0.95) -> list[dict]:
    """Each cluster with a metal colour whose metallic lies in [low, high] (largest first) refitted metal and
    dielectric (refit_pinned) from the model as it is; the model keeps the state with the lower held-out
    loss. One dict per cluster decided: its metallic before, both losses, the decision. In place."""
    if model.metal is None:
        return []
    values = model.cluster_values()["metallic"].detach()
    allowed = model.metal.allowed.bool()
    todo = [k for k in range(model.num_clusters) if allowed[k] and low <= float(values[k]) <= high]
    todo.sort(key=lambda k: -float(model.area[k]))
    train, held = held_out_frames(n_frames)
    out = []
    for k in todo:
        start = copy.deepcopy(model.state_dict())
        states, losses = {}, {}
        for metal in (True, False):
            model.load_state_dict(start)
            refit_pinned(model, env, frame_loss, train, k, metal, epochs, lr, seed=seed + k)
            losses[metal] = held_out_loss(model, env, frame_loss, held, spp)
            states[metal] = copy.deepcopy(model.state_dict())
        metal = losses[True] < losses[False]
        model.load_state_dict(states[metal])
        out.append({"cluster": k, "metallic_fitted": float(values[k]), "held_loss_metal": losses[True],
                    "held_loss_dielectric": losses[False], "decision": "metal" if metal else "dielectric"})
    return out
