"""The phase-1 texture refitted on several frames (``appearance.texture_frames``; issue 28).

Phase 1 fits the texture T on frame 0 alone, so T carries frame 0's pixel noise and no detail beyond one
frame's sampling (the plaid's weave sits at the video's Nyquist: BENCHMARKS.md "How much of the base
colour the video's pixels hold"). Here T is refitted on N frames through their meshes with the shape
phase's rasteriser (``saft.render.render_cloth``: the mip-mapped lookup and the antialiasing are the model
of a pixel's footprint), so that frame noise averages away and the frames' sub-pixel shifts against each
other constrain detail finer than one frame's pixels (multi-frame super-resolution):

    I_f = sRGB( render_cloth(V_f, lin(T), shading = g_f) )        g_f = exp(G_f↑) at the vertices
    loss = Σ_f Σ_px w_f (I_f − frame_f)² / (N · H · W · 3) + λ_T · FD(T)

T is kept in sRGB (phase 1's parametrisation, clamped to [0, 1] after each step) and linearised before the
lookup, so that the lookup's filtering and the gain act on radiance. Each frame's shading differs (the
cloth turns under the light): frame f has its own smooth gain g_f, a ``gain_grid`` × ``gain_grid`` × 3
log-gain grid over the UV square (bilinear, as GuidedMaps' gain grid), sampled at the template's vertices
and interpolated by render_cloth's per-vertex shading, fitted jointly and never multiplied into T. The
first frame of the list is the reference (g = 1): T keeps its shading, as phase 1's T keeps frame 0's,
which phase 3's gain grid divides out. w_f: the pixels inside both the frame's mask and the render's
coverage (≥ 0.99 each), so that a silhouette off by a pixel teaches the texture nothing; texels that no
such pixel sees keep their phase-1 values (T is the start). With one frame and a silhouette that matches,
the loss is phase 1's (whose mean runs over every pixel: the same normalisation).

Registration (``shift_grid``): saft's meshes are off by a fraction of a thread already in the first frames,
which blurs a weave fitted through them (the plaid 20.8 → 19.6 dB on frames 0-7); each other frame's mesh
is therefore moved in the image plane by a bilinear grid of pixel shifts, fitted jointly (frame 0's zero).
Shading (``keep_shading``): the gains start at 1 and are smooth, so in a short joint fit part of the other
frames' shading lands in T; T's low frequencies are put back to frame 0's at the end (on a plain cotton
the diffuse of phase 3 fell 30.6 → 25.8 dB without it).

``refit_texture`` (what ``appearance.texture_frames`` runs): the gate (a texture whose detail the frames
do not repeat is left alone), the frames (the first the detail test trusts) and the measured settings.
``choose_texture_frames``: the frame choices bench_texture_frames.py compares.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
import torch.nn.functional as Fnn
from scipy.ndimage import gaussian_filter

from saft.appearance.detail import FLOOR, detail_trust_test, untrusted_detail_frames
from saft.appearance.guided import GuidedMaps
from saft.appearance.params import linear_to_srgb, srgb_to_linear
from saft.render import render_cloth
from saft.render.texture_prior import finite_difference_smoothness
from saft.scene.camera import Camera

log = logging.getLogger("saft")
INTERIOR = 0.99     # a pixel teaches the texture only where the frame's mask and the render's coverage reach this


def grid_at_vertices(grid: torch.Tensor, uvs: torch.Tensor) -> torch.Tensor:
    """(B, V, C): the (B, C, g, g) grids sampled bilinearly at the vertices' UVs (OBJ convention: grid row
    0 is v = 1, the texture image's top row)."""
    xy = torch.stack([uvs[:, 0] * 2.0 - 1.0, 1.0 - uvs[:, 1] * 2.0], -1)          # grid_sample's (x, y)
    xy = xy[None, None].expand(grid.shape[0], 1, -1, -1).to(grid.dtype)
    g = Fnn.grid_sample(grid, xy, mode="bilinear", padding_mode="border", align_corners=False)  # (B, C, 1, V)
    return g[:, :, 0].permute(0, 2, 1)


def image_plane_axes(vertices: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(B, V, 2, 3): the world displacement of each vertex that moves its projection by one pixel along
    the image's x and y (the camera's axes times depth / focal length)."""
    R = torch.as_tensor(camera.rotation, dtype=vertices.dtype, device=vertices.device)
    t = torch.as_tensor(camera.translation, dtype=vertices.dtype, device=vertices.device)
    z = (vertices @ R[2] + t[2])[..., None, None]                                     # (B, V, 1, 1)
    focal = torch.tensor([camera.fx, camera.fy], dtype=vertices.dtype, device=vertices.device)
    return z * (R[:2] / focal[:, None])


def fit_texture_frames(vertices, triangles, uvs, camera: Camera, rgb, mask, frames, init_texture, *,
                       epochs: int = 100, lr: float = 0.02, lr_gain: float = 0.05, gain_grid: int = 4,
                       shift_grid: int = 0, lr_shift: float = 0.05, register_epochs: int = 0,
                       keep_shading: float = 0.0, lambda_smooth: float = 1e-4,
                       device="cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """T refitted on `frames` (module docstring). vertices (F, V, 3) of every frame; rgb (F, H, W, 3) sRGB,
    mask (F, H, W) at the camera's size; frames: indices, the first the reference (gain 1, no shift);
    init_texture (S, S, 3) sRGB, the phase-1 texture. shift_grid > 0: each other frame's mesh is also
    moved in the image plane by a shift_grid × shift_grid bilinear grid of pixel offsets over the UV square,
    fitted jointly (registration: a motion off by a fraction of a thread would blur T). The first
    register_epochs epochs (of `epochs`) fit the gains and shifts only, T held at the phase-1 texture (frame
    0's, so the other frames are registered to frame 0 before they teach T anything). keep_shading > 0:
    the fitted T's shading is put back to the start's at the end (keep_reference_shading with this σ in
    texels). Returns the texture
    (S, S, 3) sRGB float32, the log-gain grids (N, 3, g, g) and the pixel shifts (N, 2, s, s) (the
    reference's zero) and the image loss per epoch."""
    frames = [int(f) for f in frames]
    dev = torch.device(device)
    verts = torch.as_tensor(np.asarray(vertices, dtype=np.float32)[frames], device=dev)
    tri = torch.as_tensor(np.asarray(triangles), dtype=torch.int32, device=dev)
    uv = torch.as_tensor(np.asarray(uvs, dtype=np.float32), device=dev)
    target = torch.as_tensor(np.asarray(rgb, dtype=np.float32)[frames], device=dev)
    inside = torch.as_tensor(np.asarray(mask, dtype=np.float32)[frames] >= INTERIOR, device=dev)
    n, (H, W) = len(frames), target.shape[1:3]
    tex = torch.as_tensor(np.asarray(init_texture, dtype=np.float32)[..., :3], device=dev).clone().requires_grad_(True)
    log_gain = torch.zeros(max(n - 1, 0), 3, gain_grid, gain_grid, device=dev, requires_grad=True)
    shift = torch.zeros(max(n - 1, 0), 2, max(shift_grid, 1), max(shift_grid, 1), device=dev,
                        requires_grad=shift_grid > 0)
    axes = image_plane_axes(verts, camera)
    groups = [{"params": [tex], "lr": lr}, {"params": [log_gain], "lr": lr_gain}]
    opt = torch.optim.Adam(groups + ([{"params": [shift], "lr": lr_shift}] if shift_grid > 0 else []))
    with_ref = lambda a: torch.cat([a.new_zeros(1, *a.shape[1:]), a])     # the reference's zero first
    losses = []
    for epoch in range(epochs):
        opt.zero_grad(set_to_none=True)
        moved = verts + (grid_at_vertices(with_ref(shift), uv)[..., None] * axes).sum(-2) if shift_grid > 0 else verts
        gains = torch.exp(grid_at_vertices(with_ref(log_gain), uv))
        out = render_cloth(moved, tri, uv, srgb_to_linear(tex), camera, vertex_shading=gains)
        w = (inside & (out.mask.detach() >= INTERIOR)).to(target.dtype)[..., None]
        image = ((linear_to_srgb(out.rgb) - target) ** 2 * w).sum() / (n * H * W * 3)
        loss = image + lambda_smooth * finite_difference_smoothness(tex)
        loss.backward()
        if epoch < register_epochs:
            tex.grad = None          # Adam skips a parameter without a gradient: T stays as it started
        opt.step()
        with torch.no_grad():
            tex.clamp_(0.0, 1.0)
        losses.append(float(image.detach()))
    out = tex.detach().cpu().numpy()
    if keep_shading > 0:
        out = keep_reference_shading(out, init_texture, keep_shading)
    return (out, with_ref(log_gain).detach().cpu().numpy(),
            with_ref(shift).detach().cpu().numpy(), losses)


def keep_reference_shading(texture_srgb, reference_srgb, sigma: float) -> np.ndarray:
    """The texture's low frequencies put back to the reference's: in linear radiance, T · blur(R) / blur(T),
    blur a Gaussian of σ texels per channel (scipy). The gains of the other frames are smooth and start at 1,
    so in a short joint fit part of their shading lands in T instead (the low frequencies of T are pinned by
    frame 0 alone, one term of N); this keeps T in frame 0's shading (what phase 3's irradiance division and
    frame_specular assume) and leaves the detail finer than σ, where the frames' averaging and sub-pixel
    shifts act, as fitted."""
    lin = srgb_to_linear(np.asarray(texture_srgb, dtype=np.float32)[..., :3]).astype(np.float64)
    ref = srgb_to_linear(np.asarray(reference_srgb, dtype=np.float32)[..., :3]).astype(np.float64)
    blur = lambda a: gaussian_filter(a, sigma=(sigma, sigma, 0), mode="nearest")
    out = np.clip(lin * blur(ref) / np.maximum(blur(lin), 1e-4), 0.0, 1.0)
    return linear_to_srgb(torch.as_tensor(out, dtype=torch.float32)).numpy()


def guided_model(texture_srgb, smoothing: float, clusters: int, seed: int) -> GuidedMaps:
    """The texture clustered and blurred as phase 3's GuidedMaps does (what the detail test measures against)."""
    return GuidedMaps(srgb_to_linear(np.asarray(texture_srgb, dtype=np.float32)[..., :3]),
                      size=np.shape(texture_srgb)[0], clusters=clusters, seed=seed, smoothing=smoothing)


def choose_texture_frames(choice: str, count: int, texture_srgb, vertices, triangles, uvs, camera: Camera, rgb,
                          mask, trust: float = 0.5, smoothing: float = 4.0, clusters: int = 6,
                          seed: int = 0) -> list[int]:
    """`count` frame indices, frame 0 first (the reference): "first": frames 0 … count−1; "spread": evenly
    spaced over the clip; "trusted": evenly spaced over the frames whose motion lines T's detail up
    (appearance.detail: the detail repeat R_f at least `trust` × frames 1–2's; every frame where the test
    says nothing, as on a plain fabric), the texture clustered and blurred as GuidedMaps does with these
    `smoothing`, `clusters` and `seed`."""
    n_frames = len(vertices)
    count = max(1, min(int(count), n_frames))
    if choice == "first":
        return list(range(count))
    pool = np.arange(n_frames)
    if choice == "trusted":
        untrusted = untrusted_detail_frames(guided_model(texture_srgb, smoothing, clusters, seed), vertices,
                                            triangles, uvs, camera, rgb, mask, smoothing, trust)
        pool = np.setdiff1d(pool, untrusted)
    elif choice != "spread":
        raise ValueError(f"unknown frame choice {choice!r}")
    picked = pool[np.unique(np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int))]
    return [int(f) for f in picked]


# The refit's settings, measured on the appearance benchmark's plaid with saft's own motion (frames 0-7,
# texture-only diffuse PSNR; BENCHMARKS.md "The phase-1 texture refitted on several frames"): without
# registration saft's meshes blur the weave (19.6 dB against phase 1's 20.8), a 4×4 shift grid gives 20.5,
# 8×8 22.6, 12×12 23.3 (the true meshes: 24.5 unregistered, 24.3 registered at 8×8); 16 frames 22.5 (the
# later frames drift further). A gain grid of 12 (not 4) and the shading put back at σ = 8 texels: phase 3 on
# the cotton 25.8 → 28.8 dB (still below 30.6 without the refit: hence the gate in refit_texture).
EPOCHS, LR, LR_GAIN, GAIN_GRID, SHIFT_GRID, LR_SHIFT, KEEP_SHADING = 150, 0.02, 0.05, 12, 12, 0.1, 8.0


def refit_texture(vertices, triangles, uvs, camera: Camera, rgb, mask, texture_srgb, count: int, trust: float = 0.5,
                  smoothing: float = 4.0, clusters: int = 6, seed: int = 0,
                  device="cpu") -> tuple[np.ndarray, list[int]]:
    """appearance.texture_frames: the phase-1 texture (S, S, 3) sRGB refitted on the first `count` frames
    that appearance.detail trusts (their detail repeat R_f at least `trust` × frames 1-2's; T clustered
    and blurred as GuidedMaps does with `smoothing`, `clusters`, `seed`), with the settings above. A
    texture whose detail frames 1-2 do not repeat (R below detail.FLOOR: a plain fabric, whose detail is
    frame 0's noise, which phase 3's blur inside the clusters already removes) is returned as it is: there
    the refit only moved the shading (cotton, satin: BENCHMARKS.md); so is one whose detail fewer than half
    the `count` frames line up (a satin on a curved clip, refitted on frames 0-1: −2.25 dB diffuse at two
    seeds; BENCHMARKS.md "texture_frames on clips that start curved"). Returns the texture (S, S, 3) sRGB and
    the frames it was fitted on ([] when kept)."""
    if len(vertices) < 3:
        return np.asarray(texture_srgb, dtype=np.float32)[..., :3], []
    model = guided_model(texture_srgb, smoothing, clusters, seed)
    ref, untrusted = detail_trust_test(model, vertices, triangles, uvs, camera, rgb, mask, smoothing, trust)
    if ref < FLOOR:
        log.info("appearance: the phase-1 texture is kept (frames 1-2 repeat none of its detail: a plain fabric)")
        return np.asarray(texture_srgb, dtype=np.float32)[..., :3], []
    frames = [f for f in range(len(vertices)) if f not in untrusted][:int(count)]   # untrusted: a short list
    if len(frames) < max(2, int(count) // 2):   # the motion lines the detail up in too few frames to refit on
        log.info("appearance: the phase-1 texture is kept (only frames %s line its detail up)", frames)
        return np.asarray(texture_srgb, dtype=np.float32)[..., :3], []
    tex, _, _, _ = fit_texture_frames(vertices, triangles, uvs, camera, rgb, mask, frames, texture_srgb,
                                      epochs=EPOCHS, lr=LR, lr_gain=LR_GAIN, gain_grid=GAIN_GRID,
                                      shift_grid=SHIFT_GRID, lr_shift=LR_SHIFT, keep_shading=KEEP_SHADING,
                                      device=device)
    log.info("appearance: the phase-1 texture refitted on frames %s (appearance.texture_frames)", frames)
    return tex, frames
