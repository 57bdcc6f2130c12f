"""Metal or not, decided per cluster after the fit (``appearance.metal_decide``, issue 28: the lamé's threads).

The metal colour (appearance.metal) and the gate (appearance.metal_gate) let a cluster be metal, but whether
it ends metal is left to how far 150 epochs of noisy gradients carry its metallic: the lamé's gold threads
end at 0.08-0.24 on saft's own motion (a half metal whose diffuse explains most of the frames) and at 0.98
when found (BENCHMARKS "A metal colour per cluster…": "a question of travel, not of evidence"). A cloth's
thread is metal or it is not, so each metal-coloured cluster that ends between the two is refitted briefly
both ways from the fitted state, its metallic pinned at 1 (its metal colour) and at 0 (its texture), with
the env map (a metal reflects about five times as much light as the half metal the fit ended with; with
the light held, the metal never won: BENCHMARKS.md "The lamé's gold threads as metal…"). Where
the metal's image loss on frames the refits did not see is the lower, the cluster becomes metal; otherwise
the fit is left as it was: the dielectric refit is the test the metal must pass, not a verdict of its own
(forced dielectric, the lamé's threads on the true motion at seed 1 lost the half metal the fit had found:
metallic MAE 0.151 -> 0.178, relit −3 dB; BENCHMARKS.md "The lamé's gold threads as metal…").
"""

from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch

PIN = 20.0   # |metallic logit| of a pinned cluster (sigmoid(±20): 1 and 0 to 2e-9)


def held_out_frames(n_frames: int, count: int = 8) -> tuple[list[int], list[int]]:
    """(train, held): `count` evenly spaced frames held out (also the frames the evidence test scores,
    appearance.evidence), the rest to refit on (all of them if none is left)."""
    held = sorted({int(f) for f in np.linspace(0, n_frames - 1, min(n_frames, count)).round()})
    train = [f for f in range(n_frames) if f not in held]
    return (train or held), held


def _pin(model, k: int, metal: bool) -> None:
    with torch.no_grad():
        model.metal_logit[k] = (PIN if metal else -PIN) / float(model.metal_scale[k])


def _set_metallic(model, k: int, metallic: float) -> None:
    """Cluster k's metallic to this value (within sigmoid(±PIN) of 0 and 1)."""
    m = min(max(float(metallic), float(torch.sigmoid(torch.tensor(-PIN)))), float(torch.sigmoid(torch.tensor(PIN))))
    with torch.no_grad():
        model.metal_logit[k] = float(np.log(m) - np.log1p(-m)) / float(model.metal_scale[k])


def ramp_metallic(start: float, metal: bool, epoch: int, ramp: int) -> float | None:
    """The metallic the refit's epoch `epoch` (0-based) renders with on a linear ramp of `ramp` epochs from
    `start` to 1 (metal) or 0: (epoch + 1) / ramp of the way; None from the ramp's last epoch on (pinned)."""
    if epoch + 1 >= ramp:
        return None
    return start + ((1.0 if metal else 0.0) - start) * (epoch + 1) / ramp


def refit_pinned(model, env, weight: float, frame_loss: Callable, train: list[int], k: int, metal: bool,
                 epochs: int, lr: float, lr_env: float, batch: int = 3, seed: int = 0, ramp: int = 0,
                 start: float | None = None) -> None:
    """`epochs` Adam steps of every map parameter but the detail share (rate lr; appearance.detail decides
    which frames may teach it) and of the env map (rate lr_env: a metal's reflection is brighter than a half
    metal's, the light it was fitted with has to follow) on `batch` random frames of `train` each, cluster
    k's metallic pinned at 1 (metal) or 0; the shading normals stay as fitted.

    ramp > 1 (appearance.metal_decide_ramp): the metallic is not pinned at once but moved on a straight line
    from `start` (the fitted metallic) to the pin over the first `ramp` epochs, the light and the maps
    following it (a metal pinned at once with the light fitted for a half metal starts 30× the fit's loss,
    and the refit's rates do not bring it back in time).

    env: the env map module, env(weight) the map the renderer gets; frame_loss(frame, maps, env map, spp,
    seed) → scalar: the image loss of the maps rendered at that frame."""
    ramp = min(ramp, epochs) if start is not None else 0   # a ramp longer than the refit never reaches its pin

    def hold(epoch: int) -> None:   # cluster k's metallic for this epoch: on the ramp, then pinned
        m = ramp_metallic(start, metal, epoch, ramp) if ramp > 1 else None
        if m is None:
            _pin(model, k, metal)
        else:
            _set_metallic(model, k, m)

    hold(0)
    params = [p for name, p in model.named_parameters() if name != "detail_logit"]
    opt = torch.optim.Adam([{"params": params, "lr": lr}, {"params": list(env.parameters()), "lr": lr_env}])
    rng = np.random.default_rng(seed)
    for epoch in range(epochs):
        frames = rng.choice(train, min(batch, len(train)), replace=False)
        e = env(weight)
        maps = model(e)
        leaves = {name: v.detach().requires_grad_(True) for name, v in maps.items()}
        e_leaf = e.detach().requires_grad_(True)
        for f in frames:
            (frame_loss(int(f), leaves, e_leaf, 1, 104_729 + epoch * 1000 + int(f)) / len(frames)).backward()
        opt.zero_grad(set_to_none=True)
        names = [n for n in leaves if leaves[n].grad is not None]
        outs, grads = [maps[n] for n in names], [leaves[n].grad for n in names]
        if e_leaf.grad is not None:
            outs, grads = outs + [e], grads + [e_leaf.grad]
        torch.autograd.backward(outs, grads)
        for p in params + list(env.parameters()):
            if p.grad is not None and not torch.isfinite(p.grad).all():
                p.grad = None   # a Monte Carlo outlier: skip it, as the fit does
        if model.metal_logit.grad is not None:
            model.metal_logit.grad[k] = 0.0
        opt.step()
        env.clamp_()
        hold(epoch + 1)


@torch.no_grad()
def held_out_loss(model, env, weight: float, frame_loss: Callable, held: list[int], spp: int) -> float:
    """The image loss summed over the held-out frames, each rendered with a fixed seed (the same samples for
    every alternative, so that the Monte Carlo noise cancels in their difference)."""
    e = env(weight)
    maps = model(e)
    return sum(float(frame_loss(f, maps, e, spp, 7919 + f)) for f in held)


def decide_metals(model, env, weight: float, frame_loss: Callable, n_frames: int, epochs: int, lr: float,
                  lr_env: float, spp: int = 4, seed: int = 0, low: float = 0.05, high: float = 0.95,
                  ramp: int = 0, follow: bool = False, glossy: float = 0.0,
                  hues: np.ndarray | None = None) -> list[dict]:
    """Each cluster with a metal colour whose metallic lies in [low, high] (largest first) refitted metal and
    dielectric (refit_pinned) from the model and env map as they are; both keep the metal's state where its
    held-out loss is the lower, their own otherwise. One dict per cluster decided: its metallic, the held-out
    losses (fitted, each alternative pinned before and after its refit), the refits' roughness, the decision.
    ramp: refit_pinned's ramp from the cluster's metallic as it is when its turn comes. follow: once a
    cluster has become metal, the metal-coloured clusters below `low` are decided too (largest first; the rim
    of a thread whose core was found). glossy > 0: the clusters below `low` whose roughness is at most
    `glossy` are decided from the start too (a glossy dielectric with a metal colour: a metal the fit's
    gradients turned away from early, Newton's lamé). hues (K, 3) (metal_gate.highlight_hue; NaN rows: none):
    a cluster decided while its metallic is below `low` starts its metal refit with the hue of its highlights,
    not the metal colour the fit left (Adam moves that colour's logits at full rate on a gradient scaled by a
    metallic of 0.002: on Newton's lamé the gold threads' colour drifted to pink or white). In place."""
    if model.metal is None:
        return []
    values = model.cluster_values()
    metallic, rough = values["metallic"].detach(), values["roughness"].detach()
    allowed = model.metal.allowed.bool()

    def first(k: int) -> bool:   # decided from the start: a half metal, or (glossy) a glossy dielectric
        m = float(metallic[k])
        return low <= m <= high or (glossy > 0 and m < low and float(rough[k]) <= glossy)

    todo = sorted((k for k in range(model.num_clusters) if allowed[k] and first(k)), key=lambda k: -float(model.area[k]))
    train, held = held_out_frames(n_frames)
    out = []
    below = sorted((k for k in range(model.num_clusters) if allowed[k] and float(metallic[k]) < low and k not in todo),
                   key=lambda k: -float(model.area[k]))
    while todo:
        k = todo.pop(0)
        start = copy.deepcopy((model.state_dict(), env.state_dict()))
        now = float(model.cluster_values()["metallic"][k].detach())   # an earlier refit may have moved it
        row = {"cluster": k, "metallic_fitted": now,
               "held_loss_fitted": held_out_loss(model, env, weight, frame_loss, held, spp)}
        states, losses = {}, {}
        for metal, name in ((True, "metal"), (False, "dielectric")):
            model.load_state_dict(start[0])
            env.load_state_dict(start[1])
            if metal and hues is not None and now < low and np.isfinite(hues[k]).all():
                model.metal.set_hue(k, hues[k])
                row["metal_hue_from_highlights"] = [float(x) for x in hues[k]]
            _pin(model, k, metal)
            row[f"held_loss_{name}_unfitted"] = held_out_loss(model, env, weight, frame_loss, held, spp)
            refit_pinned(model, env, weight, frame_loss, train, k, metal, epochs, lr, lr_env, seed=seed + k,
                         ramp=ramp, start=now)
            losses[metal] = row[f"held_loss_{name}"] = held_out_loss(model, env, weight, frame_loss, held, spp)
            row[f"roughness_{name}"] = float(model.cluster_values()["roughness"][k].detach())
            states[metal] = copy.deepcopy((model.state_dict(), env.state_dict()))
        wins = losses[True] < losses[False]
        keep = states[True] if wins else start   # metal, or as the fit left it
        model.load_state_dict(keep[0])
        env.load_state_dict(keep[1])
        out.append({**row, "decision": "metal" if keep is states[True] else "as fitted"})
        if follow and keep is states[True] and below:
            todo, below = todo + below, []
    return out
