"""Per-parameter Adam with the reference method's gradient handling.

For every parameter tensor, separately: a step whose gradient is not finite is skipped; the gradient norm
is clipped at `clip`; then it is clipped again at the `quantile` of the last `history` norms (AutoClip,
Seetharaman et al. 2020), the current one included or, as in the reference, only the earlier ones. Each
parameter has its own Adam (own learning rate, own moments); `set_lr_factor` scales every learning rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class ParamSpec:
    name: str
    tensor: torch.Tensor
    lr: float
    betas: tuple[float, float] = (0.9, 0.999)


class ClippedAdam:
    def __init__(self, specs: list[ParamSpec], clip: float = 1e3, quantile: float = 0.75, history: int = 1000,
                 include_current: bool = True):
        self.specs = {s.name: s for s in specs}
        self.optims = {s.name: torch.optim.Adam([s.tensor], lr=s.lr, betas=s.betas) for s in specs}
        self.clip = clip
        self.quantile = quantile
        self.history_len = history
        self.include_current = include_current
        self.history: dict[str, list[float]] = {s.name: [] for s in specs}
        self.skipped: dict[str, int] = {s.name: 0 for s in specs}

    def zero_grad(self) -> None:
        for s in self.specs.values():
            s.tensor.grad = None

    @torch.no_grad()
    def step(self) -> dict[str, float]:
        """Apply one step to every parameter that has a gradient; returns the gradient norms (pre-clip)."""
        norms = {}
        for name, spec in self.specs.items():
            g = spec.tensor.grad
            if g is None:
                continue
            norm = float(torch.linalg.vector_norm(g))
            norms[name] = norm
            if not np.isfinite(norm):
                self.skipped[name] += 1
                spec.tensor.grad = None
                continue
            if norm > self.clip:
                g.mul_(self.clip / norm)
                norm = self.clip
            hist = self.history[name]
            if self.include_current:
                hist.append(norm)
            limit = float(np.quantile(hist, self.quantile)) if hist else norm
            if not self.include_current:
                hist.append(norm)
            if len(hist) > self.history_len:
                del hist[: len(hist) - self.history_len]
            if norm > limit > 0:
                g.mul_(limit / norm)
            self.optims[name].step()
        return norms

    def drop(self, name: str) -> None:
        """Stop optimizing the parameter `name` (its Adam, moments and clipping history go)."""
        for d in (self.specs, self.optims, self.history, self.skipped):
            d.pop(name, None)

    def set_lr_factor(self, factor: float) -> None:
        """Every learning rate := its initial value × factor."""
        for name, opt in self.optims.items():
            for group in opt.param_groups:
                group["lr"] = self.specs[name].lr * factor

    def state_dict(self) -> dict:
        return {"optims": {k: o.state_dict() for k, o in self.optims.items()},
                "history": {k: list(v) for k, v in self.history.items()},
                "skipped": dict(self.skipped)}

    def load_state_dict(self, state: dict) -> None:
        for k, o in self.optims.items():
            o.load_state_dict(state["optims"][k])
        self.history = {k: list(v) for k, v in state["history"].items()}
        self.skipped = dict(state["skipped"])
