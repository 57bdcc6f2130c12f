"""The light vector of the shape phase's relative shading (saft.render.shading): whether there is one, where
it starts, and whether it is learned.

shape.lr_light > 0 learns it, from shape.light_init; shape.lr_light = 0 with a non-zero shape.light_init
holds it there (a known light: the diagnostic that tells a wrong light from a wrong shading model, or a light
measured beside the video); both zero is the paper's unlit renderer (no light at all).

The plain-fabric switch (shape.plain_shading; not in the paper): shading, not point tracks, as the shape cue
of a plain fabric. On an untextured cloth the unlit shape renderer sees only the silhouette, and the optical
flow follows the shading: the few tracks that pass the forward-backward check are up to 20 px off the true
vertices in the cotton clip's large motion (frames 6-12), and at their full weight they make half of the loss.
With a known light the relative shading (saft.render.shading) halves the cotton's error only once those tracks
weigh little (BENCHMARKS.md, "Shading as the shape cue of plain cloth"). So with shape.plain_shading = Q0 > 0,
where the tracks' median texture strength Q at frame 0 (saft.reconstruct.tracks.texture_strength, in units of
the video's noise) is below Q0, the whole track loss weighs min(1, Q / shape.track_texture) also on a clip from
rest (tracks.texture_confidence weighs it so only where the clip starts curved in motion), and the light
vector (shape.lr_light, from shape.light_init) is kept; where Q >= Q0 (a textured cloth) the light is dropped
and the tracks are left as they are: the run is the unlit one. A plain fabric in a clip that starts curved in
motion (saft.scene.motion.starts_curved_in_motion: cut from the middle of its motion) is unlit too: there the
light lost (satin 3.49 -> 7.83, lamé 4.76 -> 9.55, plaid 0.95 -> 1.14, cotton 27.8 -> 20.5; BENCHMARKS.md,
"Twelfth session's defaults"). A plain fabric already moving from a flat frame 0 (a breeze from the first
frame) keeps the light and its tracks at full weight: on Newton's appearance clips that beat both the unlit
run with weighed-down tracks (2-3x lower CD2) and the light with weighed-down tracks (BENCHMARKS.md,
"Fourteenth session").
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from saft.reconstruct.context import PhaseContext
from saft.reconstruct.tracks import VertexTracks, texture_q, visible_vertices
from saft.scene.motion import starts_curved_in_motion, starts_moving

log = logging.getLogger("saft")


def light_used(cfg) -> bool:
    """Whether the shape renderer shades at all (cfg: ShapeConfig)."""
    return cfg.lr_light > 0 or any(float(v) != 0.0 for v in cfg.light_init) or cfg.light_from_above != 0.0


def light_learned(cfg) -> bool:
    return cfg.lr_light > 0


def initial_light(cfg, dtype=torch.float64, device="cpu", up: np.ndarray | None = None) -> torch.Tensor | None:
    """(3,) light vector at the start of the shape phase, or None (unlit): shape.light_init plus
    shape.light_from_above times `up`, the scene's unit up (−gravity; None where the scene states no gravity);
    requires_grad only when learned."""
    if not light_used(cfg):
        return None
    light = np.array([float(v) for v in cfg.light_init])
    if up is not None:
        light = light + cfg.light_from_above * np.asarray(up, dtype=np.float64)
    if not light_learned(cfg) and not light.any():
        return None  # a zero light held: the unlit renderer, without the shading's cost
    return torch.tensor(light, dtype=dtype, device=device, requires_grad=light_learned(cfg))


def scene_up(gravity) -> np.ndarray | None:
    """The unit vector against a stated gravity (None: not stated, or zero)."""
    if gravity is None:
        return None
    g = np.asarray(gravity, dtype=np.float64)
    norm = float(np.linalg.norm(g))
    return None if norm == 0.0 else -g / norm


def clip_texture_q(ctx: PhaseContext, template: torch.Tensor, texture: torch.Tensor) -> float:
    """Q of the clip (saft.reconstruct.tracks.texture_q) at the template's vertices visible in frame 0."""
    with torch.no_grad():
        depth0 = ctx.render(ctx.template_positions[None].to(torch.float32), texture).depth[0]
    mask0 = ctx.target_mask[0].detach().cpu().numpy()
    start, ok = visible_vertices(template, ctx.camera, mask0, depth0.detach().cpu().numpy())
    return texture_q(ctx.target_rgb[0].detach().cpu().numpy(), mask0, start, ok)


def curved_start_in_motion(ctx: PhaseContext) -> bool:
    """saft.scene.motion.starts_curved_in_motion of the run's clip and template."""
    return starts_curved_in_motion(ctx.target_mask.detach().cpu().numpy(),
                                   ctx.template_positions.detach().cpu().numpy(), ctx.triangles.cpu().numpy())


def plain_cloth(ctx: PhaseContext, state, cfg, texture: torch.Tensor, template: torch.Tensor,
                tracks: VertexTracks | None) -> VertexTracks | None:
    """Apply shape.plain_shading to the run (state: ShapeState; cfg: ShapeConfig): returns the tracks to
    use; on a textured cloth, and on a plain one in a clip that starts curved in motion, drops the light from
    state's parameters and optimizer (the unlit run, tracks untouched); on a plain one already moving from a
    flat frame 0 keeps the light and the tracks as they are. A no-op when off, or when the light is already
    gone (a resumed run of a textured cloth)."""
    if cfg.plain_shading <= 0 or state.params.light is None:
        return tracks
    q = clip_texture_q(ctx, template, texture)
    plain = q < cfg.plain_shading
    curved = plain and curved_start_in_motion(ctx)
    breeze = plain and not curved and starts_moving(ctx.target_mask.detach().cpu().numpy())
    log.info("shape.plain_shading: texture strength Q = %.3g against %g: %s", q, cfg.plain_shading,
             "textured, unlit" if not plain else "plain but the clip starts curved in motion, unlit" if curved
             else "plain, moving from flat, shaded" if breeze else "plain, shaded, tracks weighed down")
    if not plain or curved:
        state.params.light = None
        state.optimizer.drop("light")
        return tracks
    if breeze or tracks is None or cfg.track_texture <= 0:
        return tracks
    return dataclasses.replace(tracks, strength=min(tracks.strength, 1.0, q / cfg.track_texture))
