"""Phase 3 inside a run: fit the appearance on the frozen motion and write material/ (saft.appearance)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from saft.appearance import AppearanceConfig, AppearanceResult, fit_appearance, render_appearance, save_appearance
from saft.io_utils import write_image
from saft.reconstruct.context import PhaseContext
from saft.scene.camera import orbit_camera

log = logging.getLogger("saft")

NOVEL_VIEW_ANGLE = 45.0  # degrees around the vertical axis through the cloth (the paper's novel view)


def run_appearance_phase(ctx: PhaseContext, cfg: AppearanceConfig, positions: np.ndarray, triangles: np.ndarray,
                         uvs: np.ndarray, resume_state: dict | None, texture: np.ndarray | None = None) -> AppearanceResult:
    """Fit the appearance to ctx's targets on the frozen motion `positions` (F, V, 3) and save material/.
    Checkpoints through ctx.checkpoint("appearance", state); Ctrl-C through ctx.epoch_done, whose
    Interrupted leaves fit_appearance through its progress callback after it checkpointed that epoch.
    texture: the phase-1 texture (sRGB), which maps="guided" starts from."""
    log.info("appearance: profile %s, %d epochs, %s maps, image scale %g, %s frames per epoch",
             cfg.profile, cfg.epochs, cfg.maps, cfg.image_scale, cfg.frames_per_epoch or "all")
    start = int(resume_state["epoch"]) if resume_state else 0
    ctx.progress.start_phase("appearance", cfg.epochs, start)
    last = [time.perf_counter()]

    def on_progress(epochs_done: int, epochs: int, loss: float) -> None:
        epoch = epochs_done - 1
        ctx.progress.update(epoch, len(positions), loss)
        now = time.perf_counter()
        ctx.log.add(phase="appearance", epoch=epoch, frames=cfg.frames_per_epoch or len(positions),
                    loss=float(loss), image=float(loss), seconds=now - last[0])
        last[0] = now
        ctx.epoch_done("appearance", epochs_done)   # Ctrl-C: the fit checkpoints this epoch on the way out

    result = fit_appearance(positions, triangles, uvs, ctx.camera, ctx.target_rgb.cpu().numpy(),
                            ctx.target_mask.cpu().numpy(), config=cfg, device=ctx.devices.appearance, progress=on_progress,
                            resume_state=resume_state,
                            checkpoint=lambda app_state: ctx.checkpoint("appearance", app_state),
                            init_texture=texture)
    ctx.progress.end_phase()
    save_appearance(result, ctx.out_dir)
    return result


def write_appearance_renders(out_dir: Path, result, positions: np.ndarray, triangles, uvs, camera, target_rgb,
                             device) -> None:
    """material/renders/frame_XXX.png (re-render | target) and material/novel_view/frame_XXX.png (45°)."""
    mat = Path(out_dir) / "material"
    renders = render_appearance(result, positions, triangles, uvs, camera, device=device)
    for i, img in enumerate(renders):
        write_image(mat / "renders" / f"frame_{i:03d}.png", np.concatenate([img, target_rgb[i]], axis=1))
    center = positions[0].mean(axis=0)
    novel = orbit_camera(camera, center, NOVEL_VIEW_ANGLE)
    views = render_appearance(result, positions, triangles, uvs, novel, device=device)
    for i, img in enumerate(views):
        write_image(mat / "novel_view" / f"frame_{i:03d}.png", img)
    write_image(mat / "novel_view.png", views[0])
