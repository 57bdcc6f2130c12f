"""Phase 1, texture mapping: fit a texture on frame 0 with the template geometry (paper section 3.3.1).

loss = mean squared RGB error on frame 0 + λ_T · FD(T); Adam; texels clamped to [0, 1] after each step.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from saft.reconstruct.config import TextureConfig
from saft.reconstruct.context import PhaseContext
from saft.reconstruct.losses import image_loss
from saft.render.texture_prior import finite_difference_smoothness


@dataclass
class TextureState:
    texture: torch.Tensor           # (S, S, 3) float32 sRGB, row 0 = top of the texture image (v = 1)
    optimizer: torch.optim.Adam
    epoch: int = 0

    def state_dict(self) -> dict:
        return {"texture": self.texture.detach().cpu(), "optimizer": self.optimizer.state_dict(), "epoch": self.epoch}


def initial_texture(cfg: TextureConfig, scene_texture: np.ndarray | None, device) -> torch.Tensor:
    if cfg.init_from_scene and scene_texture is not None:
        t = torch.from_numpy(np.ascontiguousarray(scene_texture[:, :, :3], dtype=np.float32))
        t = F.interpolate(t.permute(2, 0, 1)[None], size=(cfg.size, cfg.size), mode="area"
                          if t.shape[0] >= cfg.size else "bilinear")[0].permute(1, 2, 0)
        return t.clamp(0, 1).contiguous().to(device)
    return torch.full((cfg.size, cfg.size, 3), float(cfg.init_value), dtype=torch.float32, device=device)


def new_texture_state(cfg: TextureConfig, scene_texture, device) -> TextureState:
    tex = initial_texture(cfg, scene_texture, device).requires_grad_(True)
    return TextureState(tex, torch.optim.Adam([tex], lr=cfg.lr))


def restore_texture_state(cfg: TextureConfig, saved: dict, device) -> TextureState:
    tex = saved["texture"].to(device).requires_grad_(True)
    state = TextureState(tex, torch.optim.Adam([tex], lr=cfg.lr), saved["epoch"])
    state.optimizer.load_state_dict(saved["optimizer"])
    return state


def run_texture_phase(ctx: PhaseContext, cfg: TextureConfig, state: TextureState) -> torch.Tensor:
    """Optimize until cfg.epochs (continuing from state.epoch); returns the fitted texture (detached)."""
    template = ctx.template_positions.to(torch.float32)
    target_rgb = ctx.target_rgb[:1]
    ctx.progress.start_phase("texture", cfg.epochs, state.epoch)
    while state.epoch < cfg.epochs:
        t0 = time.perf_counter()
        state.optimizer.zero_grad(set_to_none=True)
        out = ctx.render(template[None], state.texture)
        l_img = image_loss(out.rgb, target_rgb)
        l_smooth = finite_difference_smoothness(state.texture)
        loss = l_img + cfg.lambda_smooth * l_smooth
        loss.backward()
        state.optimizer.step()
        with torch.no_grad():
            state.texture.clamp_(0.0, 1.0)
        state.epoch += 1
        value = float(loss.detach())
        ctx.log.add(phase="texture", epoch=state.epoch - 1, frames=1, loss=value, image=float(l_img.detach()),
                    smooth=float(l_smooth.detach()), seconds=time.perf_counter() - t0)
        ctx.progress.update(state.epoch - 1, 1, value)
        ctx.epoch_done("texture", state.epoch, state.state_dict)
    ctx.progress.end_phase()
    return state.texture.detach()
