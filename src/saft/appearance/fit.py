"""Phase 3: fit SVBRDF maps + environment map to the video with the motion frozen; re-render; save."""

from __future__ import annotations

import copy
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as Fnn

from saft.appearance.config import AppearanceConfig
from saft.appearance.detail import untrusted_detail_frames
from saft.appearance.evidence import cluster_evidence, undetermined_note
from saft.appearance.frame_specular import FRAME_GRID, FrameStack, frame_specular
from saft.appearance.guided import GuidedMaps
from saft.appearance.irradiance import FrameZeroIrradiance, IrradianceMaps
from saft.appearance.metal_decide import decide_metals, held_out_frames
from saft.appearance.metal_gate import metal_scores
from saft.appearance.mitsuba_backend import load_mitsuba
from saft.appearance.normals import NormalCorrection
from saft.appearance.tolerant import blurred_linearised_mse
from saft.appearance.params import (EnvironmentMap, PyramidEnvironmentMap, TexelMaps, TextureDecoder, colour_weight,
                                    env_amplitude, env_smoothness, linear_to_srgb, srgb_to_linear)
from saft.appearance.renderer import ClothRenderer
from saft.appearance.texture_frames import refit_texture
from saft.errors import SaftInputError
from saft.io_utils import atomic_path, atomic_write_json, read_image, resize_images, write_image
from saft.scene.camera import Camera
from saft.scene.motion import starts_curved_in_motion


@dataclass
class AppearanceResult:
    """What phase 3 produces. Maps row 0 = TOP of the texture (OBJ convention, v = 1); all numpy float32.

    diffuse (S, S, 3) linear albedo, roughness (S, S), metallic (S, S), envmap (He, We, 3) linear radiance
    (the map as rendered at the last epoch, i.e. after the colour schedule), losses: the image loss (masked
    sRGB MSE, mean over the epoch's frames) per epoch.
    """

    diffuse: np.ndarray
    roughness: np.ndarray
    metallic: np.ndarray
    envmap: np.ndarray
    losses: list[float]
    config: AppearanceConfig
    seconds: float = 0.0              # wall-clock time of the fit
    cpu_seconds: float = 0.0          # CPU time of this process (all threads) during the fit
    state: dict | None = field(default=None, repr=False)
    # maps="guided": per material cluster, its area, roughness, metallic and whether the video determined
    # it (appearance.evidence); None for the other parametrisations
    materials: list[dict] | None = None
    # maps="guided" with detail_trust > 0: the frames left out of the detail share's gradient (appearance.detail)
    detail_frames_left_out: list[int] | None = None


def _build_model(cfg: AppearanceConfig, init_texture, frame0=None) -> torch.nn.Module:
    """frame0: (vertices (V, 3), triangles, uvs, camera) of frame 0, for diffuse_shading="irradiance"."""
    if cfg.maps == "guided":
        if init_texture is None:
            raise SaftInputError("appearance.maps", "'guided' maps start from the phase-1 texture; none was given")
        kw = dict(size=cfg.texel_size, gain_grid=cfg.gain_grid, clusters=cfg.clusters, min_roughness=cfg.min_roughness,
                  init_roughness=cfg.init_roughness, init_metallic=cfg.init_metallic, seed=cfg.seed,
                  smoothing=cfg.texture_smoothing)
        texture = srgb_to_linear(np.asarray(init_texture, dtype=np.float32)[..., :3])
        if cfg.diffuse_shading == "irradiance":
            e0 = FrameZeroIrradiance(*frame0, env_shape=(cfg.env_height, cfg.env_width))
            return IrradianceMaps(texture, e0, **kw)
        return GuidedMaps(texture, **kw)
    init = dict(min_roughness=cfg.min_roughness, init_diffuse=cfg.init_diffuse, init_roughness=cfg.init_roughness,
                init_metallic=cfg.init_metallic)
    if cfg.maps == "decoder":
        return TextureDecoder(tile_size=cfg.tile_size, num_tiles=cfg.num_tiles, overlap=cfg.tile_overlap,
                              latent_channels=cfg.latent_channels, seed=cfg.seed, **init)
    return TexelMaps(size=cfg.texel_size, **init)


def _snap(a: np.ndarray, value: float, tol: float = 1e-6) -> np.ndarray:
    """float32 copy with entries within tol of `value` set to it exactly (a cluster set to matte by the
    evidence test is sigmoid(±20), not exactly 1 or 0)."""
    return np.where(np.abs(a - value) < tol, value, a).astype(np.float32)


def _resize_targets(rgb: np.ndarray, mask: np.ndarray, camera: Camera, scale: float):
    rgb_t = torch.as_tensor(np.asarray(rgb, dtype=np.float32))
    mask_t = torch.as_tensor(np.asarray(mask, dtype=np.float32))
    if scale >= 1.0:
        return rgb_t, mask_t, camera
    cam = camera.scaled(scale)
    return resize_images(rgb_t, cam.height, cam.width), resize_images(mask_t, cam.height, cam.width), cam


def masked_srgb_mse(pred_linear: torch.Tensor, target_srgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared sRGB error inside the (soft) mask."""
    diff = (linear_to_srgb(pred_linear) - target_srgb) ** 2
    w = mask[..., None]
    return (diff * w).sum() / (w.sum() * 3.0).clamp_min(1e-8)


def srgb_slope(target_srgb: torch.Tensor, max_slope: float = 12.92) -> torch.Tensor:
    """d sRGB / d linear evaluated at the target colour (clamped), for the linearised sRGB loss."""
    lin = srgb_to_linear(target_srgb.clamp(0.0, 1.0))
    slope = torch.where(lin <= 0.0031308, torch.full_like(lin, 12.92),
                        (1.055 / 2.4) * lin.clamp_min(0.0031308) ** (1.0 / 2.4 - 1.0))
    return slope.clamp(max=max_slope)


def masked_linearised_srgb_mse(pred_linear: torch.Tensor, target_linear: torch.Tensor, slope: torch.Tensor,
                               mask: torch.Tensor) -> torch.Tensor:
    """The sRGB MSE to first order around the target: mean (sRGB'(t)·(x − t))² inside the mask.

    Unlike the plain sRGB MSE it is quadratic in the rendered radiance, so with Mitsuba's decorrelated
    primal/adjoint samples its gradient is unbiased even at 1 spp (the plain sRGB loss of a 1-spp image is
    biased by the concave sRGB curve: fits come out too bright).
    """
    diff = (slope * (pred_linear - target_linear)) ** 2
    w = mask[..., None]
    return (diff * w).sum() / (w.sum() * 3.0).clamp_min(1e-8)


def _square_pixels(camera: Camera) -> Camera:
    """Mitsuba needs fx == fy. A camera whose pixels are not square (R1: fx/fy = 1.029) is replaced by the
    camera of the image resampled vertically to square pixels (height·fx/fy rows); a remaining rounding
    ratio below 1 % is absorbed by using the mean focal length."""
    if camera.fx == camera.fy:
        return camera
    cam = camera
    if abs(camera.fx - camera.fy) > 0.005 * camera.fx:
        height = max(1, int(round(camera.height * camera.fx / camera.fy)))
        sy = height / camera.height
        K = camera.K.copy()
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        cam = Camera(K, camera.world_to_camera, camera.width, height)
    K = cam.K.copy()
    K[0, 0] = K[1, 1] = 0.5 * (cam.fx + cam.fy)
    return Camera(K, cam.world_to_camera, cam.width, cam.height)


def fit_appearance(vertices_per_frame, triangles, uvs, camera: Camera, target_rgb, target_mask,
                   config: AppearanceConfig | None = None, device="cpu",
                   progress: Callable[[int, int, float], None] | None = None,
                   resume_state: dict | None = None,
                   checkpoint: Callable[[dict], None] | None = None, init_texture=None) -> AppearanceResult:
    """Estimate diffuse/roughness/metallic maps and an environment map from frames with frozen geometry.

    vertices_per_frame (F, V, 3) world positions; triangles (T, 3); uvs (V, 2) OBJ convention; camera: the
    OpenCV camera of the frames; target_rgb (F, H, W, 3) sRGB in [0, 1]; target_mask (F, H, W) in [0, 1].
    progress(epoch, epochs, loss) is called after each epoch; checkpoint(state) every
    config.checkpoint_every epochs and at the end, with a state dict that `resume_state=` continues from.
    progress may raise (e.g. on Ctrl-C) to stop the fit: checkpoint(state) is called with the state after
    that epoch before the exception goes on, so an interruption loses no finished epoch.
    init_texture: the phase-1 texture (St, St, 3) sRGB, which maps="guided" starts from (required there).
    """
    cfg = copy.deepcopy(config) if config is not None else AppearanceConfig()
    cfg.validate()
    verts = np.asarray(vertices_per_frame, dtype=np.float64)
    if verts.ndim != 3 or verts.shape[2] != 3:
        raise SaftInputError("vertices_per_frame", f"expected (F, V, 3), got {verts.shape}")
    rgb = np.asarray(target_rgb, dtype=np.float32)
    mask = np.asarray(target_mask, dtype=np.float32)
    n_frames = verts.shape[0]
    if rgb.shape[:1] != (n_frames,) or rgb.ndim != 4 or rgb.shape[3] != 3 or mask.shape != rgb.shape[:3]:
        raise SaftInputError("target_rgb", f"frames {rgb.shape} / masks {mask.shape} do not match {n_frames} "
                                           "frames of (H, W, 3) / (H, W)")
    if rgb.shape[1:3] != (camera.height, camera.width):
        raise SaftInputError("target_rgb", f"images are {rgb.shape[2]}x{rgb.shape[1]}, the camera is "
                                           f"{camera.width}x{camera.height}")
    dev = torch.device(device)
    rgb_t, mask_t, cam = _resize_targets(rgb, mask, camera, cfg.image_scale)
    cam = _square_pixels(cam)
    rgb_t, mask_t = resize_images(rgb_t, cam.height, cam.width), resize_images(mask_t, cam.height, cam.width)
    rgb_t, mask_t = rgb_t.to(dev), mask_t.to(dev)
    lin_t = srgb_to_linear(rgb_t.clamp(0.0, 1.0))
    slope_t = srgb_slope(rgb_t)

    refit_s = (time.perf_counter(), time.process_time())     # the texture's refit counts as part of the fit
    if cfg.texture_frames > 1 and init_texture is not None:   # the phase-1 texture refitted on several frames
        init_texture, _ = refit_texture(verts, triangles, uvs, camera, rgb, mask, init_texture, cfg.texture_frames,
                                        max(cfg.detail_trust, 0.5), cfg.texture_smoothing, cfg.clusters, cfg.seed,
                                        device=dev)
    refit_s = (time.perf_counter() - refit_s[0], time.process_time() - refit_s[1])
    torch.manual_seed(cfg.seed)
    model = _build_model(cfg, init_texture, (verts[0], triangles, uvs, camera)).to(dev)
    left_out = None   # the frames that do not teach the detail share (appearance.detail); None: not tested
    if isinstance(model, GuidedMaps) and cfg.detail_trust > 0:
        left_out = untrusted_detail_frames(model, verts, triangles, uvs, camera, rgb, mask, cfg.texture_smoothing,
                                           cfg.detail_trust)
    scores, hues = None, None   # the gate's scores and the highlights' hues per cluster (appearance.metal_gate)
    if isinstance(model, GuidedMaps) and cfg.metal_colour:   # a metal colour per cluster (appearance.metal)
        if cfg.metal_gate > 0:
            scores, hues = metal_scores(model, verts, triangles, uvs, camera, rgb, mask)
            if not (cfg.metal_decide > 0 and cfg.metal_decide_glossy > 0):   # the hues start only a glossy refit
                hues = None
        model.use_metal_colour(cfg.metal_rate, None if scores is None else scores >= cfg.metal_gate)   # NaN: no
    untrusted = set(left_out or ())
    stack = None   # the frames in texture space that measure frame 0's specular (appearance.frame_specular)
    if isinstance(model, IrradianceMaps) and cfg.frame_specular > 1:
        picked = np.linspace(0, n_frames - 1, min(cfg.frame_specular, n_frames)).round().astype(int)
        stack = FrameStack(verts, triangles, uvs, camera, rgb, mask, FRAME_GRID, (cfg.env_height, cfg.env_width),
                           picked)
    if cfg.env_levels > 1:
        env = PyramidEnvironmentMap(cfg.env_height, cfg.env_width, cfg.env_levels, cfg.env_init, cfg.env_min).to(dev)
    else:
        env = EnvironmentMap(cfg.env_height, cfg.env_width, cfg.env_init, cfg.env_min).to(dev)
    if cfg.maps == "decoder":
        opt_maps = torch.optim.Adam(model.parameters(), lr=cfg.lr_decoder, betas=tuple(cfg.betas_decoder))
    else:
        opt_maps = torch.optim.Adam(model.parameters(), lr=cfg.lr_texels)
    opt_env = torch.optim.Adam(env.parameters(), lr=cfg.lr_env, betas=tuple(cfg.betas_env))
    normals = None   # the learnt shading-normal correction (appearance.normals); None: the meshes' own
    correct_normals = cfg.normal_grid > 0
    if correct_normals and starts_curved_in_motion(mask, verts[0], triangles):   # not on a clip cut mid-motion:
        # it lost twice there
        logging.getLogger("saft").info("appearance.normal_grid: the clip starts curved in motion, normals left as "
                                       "they are")
        correct_normals = False
    if correct_normals:
        normals = NormalCorrection(verts, triangles, uvs, cfg.normal_grid, cfg.normal_keys).to(dev)
        opt_normals = torch.optim.Adam(normals.parameters(), lr=cfg.lr_normals)
    shading = (lambda f: None) if normals is None else (lambda f: normals(int(f)))
    losses: list[float] = []
    start_epoch = 0
    if resume_state is not None:
        model.load_state_dict(resume_state["model"])
        env.load_state_dict(resume_state["env"])
        opt_maps.load_state_dict(resume_state["opt_maps"])
        opt_env.load_state_dict(resume_state["opt_env"])
        if normals is not None:
            normals.load_state_dict(resume_state["normals"])
            opt_normals.load_state_dict(resume_state["opt_normals"])
        losses = list(resume_state["losses"])
        start_epoch = int(resume_state["epoch"])

    size = model.size
    renderer = ClothRenderer(triangles, uvs, cam, device=dev, max_depth=cfg.max_depth, map_shape=(size, size),
                             env_shape=(cfg.env_height, cfg.env_width))

    def state(epoch: int) -> dict:
        return {"epoch": epoch, "model": copy.deepcopy(model.state_dict()), "env": copy.deepcopy(env.state_dict()),
                "opt_maps": copy.deepcopy(opt_maps.state_dict()), "opt_env": copy.deepcopy(opt_env.state_dict()),
                "losses": list(losses), "config": cfg.to_dict(),
                **({} if normals is None else {"normals": copy.deepcopy(normals.state_dict()),
                                               "opt_normals": copy.deepcopy(opt_normals.state_dict())})}

    t0, c0 = time.perf_counter(), time.process_time()
    batch = cfg.frames_per_epoch if 0 < cfg.frames_per_epoch < n_frames else n_frames
    base_lrs = [cfg.lr_decoder if cfg.maps == "decoder" else cfg.lr_texels, cfg.lr_env]  # (resume: not the decayed)
    for epoch in range(start_epoch, cfg.epochs):
        w = colour_weight(epoch, cfg.epochs, cfg.grey_fraction, cfg.blend_fraction)
        decay = cfg.lr_final_factor ** (epoch / max(cfg.epochs - 1, 1))  # exponential: 1 → lr_final_factor
        for opt, lr in zip((opt_maps, opt_env), base_lrs):
            for g in opt.param_groups:
                g["lr"] = lr * decay
        if normals is not None:
            opt_normals.param_groups[0]["lr"] = cfg.lr_normals * decay
            opt_normals.zero_grad(set_to_none=True)   # the frames' renders put their gradients here directly
        if batch < n_frames:
            frames = np.sort(np.random.default_rng(cfg.seed * 100_003 + epoch).choice(n_frames, batch, replace=False))
        else:
            frames = np.arange(n_frames)
        env_eff = env(w)
        if stack is not None:
            model.set_specular0(frame_specular(stack, env_eff.detach().cpu())[0])
        maps = model(env_eff)   # IrradianceMaps: the diffuse depends on the env map too
        leaves = {k: v.detach().requires_grad_(True) for k, v in maps.items()}
        env_leaf = env_eff.detach().requires_grad_(True)
        epoch_loss = 0.0
        dropped = None
        for f in frames:
            if f in untrusted:
                before = leaves["diffuse"].grad.clone() if leaves["diffuse"].grad is not None else 0.0
            renderer.set_vertices(verts[f])
            img = renderer.render(leaves["diffuse"], leaves["roughness"], leaves["metallic"], env_leaf,
                                  spp=cfg.spp, seed=epoch * n_frames + int(f), normals=shading(f))
            if cfg.loss == "srgb":
                loss = masked_srgb_mse(img, rgb_t[f], mask_t[f])
                report = loss
            else:
                loss = masked_linearised_srgb_mse(img, lin_t[f], slope_t[f], mask_t[f])
                if cfg.loss_blur > 0:
                    blurred = blurred_linearised_mse(img, lin_t[f], slope_t[f], mask_t[f], cfg.loss_blur)
                    loss = (1.0 - cfg.loss_blur_weight) * loss + cfg.loss_blur_weight * blurred
                with torch.no_grad():
                    report = masked_srgb_mse(img, rgb_t[f], mask_t[f])
            (loss / len(frames)).backward()
            if f in untrusted:
                dropped = (leaves["diffuse"].grad - before) + (0.0 if dropped is None else dropped)
            epoch_loss += float(report.detach()) / len(frames)
        if dropped is not None:   # take the untrusted frames' part out of the detail share's gradient
            dropped = torch.autograd.grad(maps["diffuse"], model.detail_logit, dropped, retain_graph=True)[0]
        reg = cfg.lambda_env_l1 * env_amplitude(env_eff) + cfg.lambda_env_smooth * env_smoothness(env_eff)
        if isinstance(model, GuidedMaps):
            reg = reg + model.metal_prior(cfg.lambda_metallic_l1, cfg.lambda_metal_blend)
            if cfg.lambda_gain_chroma > 0:
                reg = reg + cfg.lambda_gain_chroma * model.gain_chroma()
        if normals is not None:
            reg = reg + cfg.lambda_normals * normals.penalty()
        opt_maps.zero_grad(set_to_none=True)
        opt_env.zero_grad(set_to_none=True)
        outs = [maps[k] for k in leaves] + [env_eff]
        grads = [leaves[k].grad if leaves[k].grad is not None else torch.zeros_like(leaves[k]) for k in leaves]
        grads.append(env_leaf.grad if env_leaf.grad is not None else torch.zeros_like(env_leaf))
        torch.autograd.backward(outs + [reg], grads + [torch.ones_like(reg)])
        if dropped is not None and model.detail_logit.grad is not None:
            model.detail_logit.grad -= dropped
        learnt = list(model.parameters()) + list(env.parameters()) + list(() if normals is None else normals.parameters())
        for p in learnt:
            if p.grad is not None and not torch.isfinite(p.grad).all():
                p.grad = None  # skip a non-finite step (Monte Carlo outlier)
        opt_maps.step()
        opt_env.step()
        if normals is not None:
            opt_normals.step()
        env.clamp_()
        losses.append(epoch_loss)
        if progress is not None:
            try:
                progress(epoch + 1, cfg.epochs, epoch_loss)
            except BaseException:   # progress stops the fit (Ctrl-C): keep this epoch's state first
                if checkpoint is not None:
                    checkpoint(state(epoch + 1))
                raise
        if checkpoint is not None and cfg.checkpoint_every > 0 and (epoch + 1) % cfg.checkpoint_every == 0 \
                and epoch + 1 < cfg.epochs:
            checkpoint(state(epoch + 1))

    evidence = None
    final_weight = colour_weight(cfg.epochs - 1, cfg.epochs, cfg.grey_fraction, cfg.blend_fraction)

    def render_frame(f, d, r, m, e, spp, seed):
        renderer.set_vertices(verts[f])
        with torch.no_grad():
            n = shading(f)
        return renderer.render(d, r, m, e, spp=spp, seed=seed, normals=n)

    def frame_error(f, img):   # the fit's image loss of a render of frame f
        return masked_linearised_srgb_mse(img, lin_t[f], slope_t[f], mask_t[f])

    decisions = []   # metal or not per half-metal cluster (appearance.metal_decide)
    if isinstance(model, GuidedMaps) and cfg.metal_decide > 0:
        decisions = decide_metals(model, env, final_weight,
                                  lambda f, m, e, spp, seed: frame_error(f, render_frame(
                                      f, m["diffuse"], m["roughness"], m["metallic"], e, spp, seed)),
                                  n_frames, cfg.metal_decide,
                                  cfg.lr_texels * cfg.lr_final_factor ** 0.5, cfg.lr_env * cfg.lr_final_factor ** 0.5,
                                  cfg.evidence_spp, cfg.seed, ramp=cfg.metal_decide_ramp,
                                  follow=cfg.metal_decide_follow,
                                  glossy=cfg.metal_decide_glossy, hues=hues)
    env_now = env(final_weight).detach()   # after the decisions, which refit the env map
    if isinstance(model, GuidedMaps) and cfg.evidence_threshold > 0:
        evidence = cluster_evidence(model, env_now, render_frame, held_out_frames(n_frames)[1], frame_error,
                                    spp=cfg.evidence_spp, threshold=cfg.evidence_threshold,
                                    band=cfg.undetermined_roughness == "band")
        if model.metal is not None:   # each cluster's metal colour, and the gate's verdict
            for row, c, a in zip(evidence, model.metal.colours().tolist(), model.metal.allowed.tolist()):
                row.update(metal_colour=c, metal_allowed=bool(a),
                           **({} if scores is None else {"highlight_colour": float(scores[row["cluster"]])}))
        for d in decisions:
            evidence[d["cluster"]]["metal_decision"] = d
    final_state = state(cfg.epochs)
    if checkpoint is not None:
        checkpoint(final_state)
    with torch.no_grad():
        env_final = env(final_weight)
        maps = model(env_final)
        out_shape = (cfg.env_output_height, cfg.env_output_width)
        if tuple(env_final.shape[:2]) != out_shape:
            env_final = Fnn.interpolate(env_final.permute(2, 0, 1)[None], size=out_shape, mode="bilinear",
                                        align_corners=False)[0].permute(1, 2, 0).clamp_min(cfg.env_min)
    return AppearanceResult(
        diffuse=maps["diffuse"].cpu().numpy().astype(np.float32),
        roughness=_snap(maps["roughness"].cpu().numpy(), 1.0),
        metallic=_snap(maps["metallic"].cpu().numpy(), 0.0),
        envmap=env_final.cpu().numpy().astype(np.float32),
        losses=losses,
        config=cfg,
        seconds=time.perf_counter() - t0 + refit_s[0],
        cpu_seconds=time.process_time() - c0 + refit_s[1],
        state=final_state,
        materials=evidence,
        detail_frames_left_out=left_out,
    )


# ---------------------------------------------------------------------------------------------- rendering
def render_appearance(result: AppearanceResult, vertices, triangles, uvs, camera: Camera, spp: int | None = None,
                      device="cpu", seed: int = 0) -> np.ndarray:
    """Re-render with the estimated appearance: sRGB float32 (H, W, 3) for vertices (V, 3), or (F, H, W, 3)
    for (F, V, 3). Black background. spp defaults to result.config.render_spp."""
    v = np.asarray(vertices, dtype=np.float64)
    single = v.ndim == 2
    v = v[None] if single else v
    spp = int(spp or result.config.render_spp)
    renderer = ClothRenderer(triangles, uvs, _square_pixels(camera), device=device,
                             max_depth=result.config.max_depth, map_shape=result.roughness.shape,
                             env_shape=result.envmap.shape[:2])
    maps = [torch.as_tensor(a) for a in (result.diffuse, result.roughness, result.metallic, result.envmap)]
    out = []
    with torch.no_grad():
        for f in range(v.shape[0]):
            renderer.set_vertices(v[f])
            img = renderer.render(*maps, spp=spp, seed=seed + f)
            out.append(linear_to_srgb(img).cpu())
    # back to the camera's own pixel grid when it was resampled to square pixels
    out = resize_images(torch.stack(out), camera.height, camera.width).numpy().astype(np.float32)
    return out[0] if single else out


# ---------------------------------------------------------------------------------------------- output
def write_exr(path: Path, image: np.ndarray) -> None:
    """Write a float32 RGB EXR atomically (Mitsuba's Bitmap writer: no extra Python dependency)."""
    mi = load_mitsuba("cpu")
    with atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)).write(str(tmp))


def read_exr(path: Path) -> np.ndarray:
    """A float32 RGB EXR as an array (Mitsuba's Bitmap reader)."""
    mi = load_mitsuba("cpu")
    return np.array(mi.Bitmap(str(path)), dtype=np.float32)


def env_preview(envmap: np.ndarray) -> np.ndarray:
    """A displayable sRGB preview of a linear env map (scaled so its 99th percentile is white)."""
    scale = max(float(np.percentile(envmap, 99)), 1e-6)
    return linear_to_srgb(torch.as_tensor(envmap / scale)).numpy()


def save_appearance(result: AppearanceResult, out_dir) -> dict[str, Path]:
    """Write DIR/material/{diffuse,roughness,metallic}.png, envmap.exr, envmap.png and appearance.json.

    diffuse.png is sRGB-encoded (as texture files usually are); roughness/metallic are stored linearly;
    envmap.exr is linear float radiance; envmap.png is a tone-mapped preview. Every file is written
    atomically. Returns the paths.
    """
    mat = Path(out_dir) / "material"
    paths = {name: mat / f"{name}.png" for name in ("diffuse", "roughness", "metallic")}
    paths["envmap"] = mat / "envmap.exr"
    paths["envmap_preview"] = mat / "envmap.png"
    paths["summary"] = mat / "appearance.json"
    write_image(paths["diffuse"], linear_to_srgb(torch.as_tensor(result.diffuse)).numpy())
    write_image(paths["roughness"], result.roughness)
    write_image(paths["metallic"], result.metallic)
    write_exr(paths["envmap"], result.envmap)
    write_image(paths["envmap_preview"], env_preview(result.envmap))
    summary = {"config": result.config.to_dict(), "losses": result.losses, "seconds": result.seconds,
               "cpu_seconds": result.cpu_seconds}
    if result.materials is not None:
        summary["materials"] = result.materials
        summary["undetermined"] = undetermined_note(result.materials)
    if result.detail_frames_left_out is not None:
        summary["detail_frames_left_out"] = result.detail_frames_left_out
    atomic_write_json(paths["summary"], summary)
    return paths


def load_appearance(out_dir) -> AppearanceResult:
    """Read what save_appearance wrote (8-bit maps: quantised) back into an AppearanceResult."""
    mat = Path(out_dir) / "material"
    summary = json.loads((mat / "appearance.json").read_text())
    cfg = AppearanceConfig.from_dict(summary.get("config", {}), str(mat / "appearance.json"))
    return AppearanceResult(
        diffuse=srgb_to_linear(read_image(mat / "diffuse.png")[..., :3]),
        roughness=np.maximum(read_image(mat / "roughness.png")[..., 0], cfg.min_roughness),
        metallic=read_image(mat / "metallic.png")[..., 0],
        envmap=read_exr(mat / "envmap.exr")[..., :3],
        losses=list(summary.get("losses", [])),
        config=cfg,
        seconds=float(summary.get("seconds", 0.0)),
        cpu_seconds=float(summary.get("cpu_seconds", 0.0)),
        materials=summary.get("materials"),
        detail_frames_left_out=summary.get("detail_frames_left_out"),
    )
