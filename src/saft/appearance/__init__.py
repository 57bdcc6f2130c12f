"""saft.appearance — phase 3: SVBRDF maps and environment light by differentiable ray tracing (Mitsuba 3).

With the motion frozen, a two-sided principled (metallic-roughness) BSDF fed by diffuse/roughness/metallic
maps and a lat-long environment map are fitted to the video by Monte Carlo ray tracing (Mitsuba's ``prb``
integrator, black background, gradients to the maps and the env map only).

API
---
``fit_appearance(vertices_per_frame, triangles, uvs, camera, target_rgb, target_mask, config=None,
device="cpu", progress=None, resume_state=None, checkpoint=None) -> AppearanceResult``
    vertices_per_frame (F, V, 3); triangles (T, 3); uvs (V, 2) OBJ convention (v up); camera: the OpenCV
    :class:`saft.scene.camera.Camera` of the frames; target_rgb (F, H, W, 3) sRGB in [0, 1]; target_mask
    (F, H, W). ``progress(epoch, epochs, loss)`` after every epoch; ``checkpoint(state)`` every
    ``config.checkpoint_every`` epochs and at the end with a plain dict (epoch, model/env/optimizer state
    dicts, losses, config) that ``resume_state=`` continues from (``torch.save`` it).
``AppearanceResult``: diffuse (S, S, 3) linear albedo, roughness (S, S), metallic (S, S), envmap
    (256, 512, 3) linear radiance, losses (per epoch: masked sRGB MSE of the 1-spp renders), config,
    seconds, state. Maps are numpy float32, row 0 = TOP of the texture image (UV v = 1).
``render_appearance(result, vertices, triangles, uvs, camera, spp=None, device="cpu", seed=0)``
    sRGB re-render(s): (H, W, 3) for (V, 3) vertices, (F, H, W, 3) for (F, V, 3).
``save_appearance(result, out_dir)`` → DIR/material/diffuse.png (sRGB-encoded), roughness.png,
    metallic.png, envmap.exr (linear float, written with Mitsuba's Bitmap: no extra dependency),
    envmap.png (preview), appearance.json; atomically. ``load_appearance(out_dir)`` reads them back.
``AppearanceConfig`` (paper defaults), ``paper_profile()``, ``cpu_profile(base=None)``,
    ``profile_for_device(device, base=None)`` (CPU → cpu_profile).
``ClothRenderer(triangles, uvs, camera, device, max_depth=2, map_shape, env_shape)``: ``set_vertices(v)``
    per frame (updates positions + normals through ``mi.traverse``, no rebuild), ``render(diffuse,
    roughness, metallic, env, spp, seed)`` → linear (H, W, 3) torch tensor, differentiable in the inputs.
``TextureDecoder``, ``TexelMaps``, ``EnvironmentMap``, ``colour_weight`` (grey → blend → colour schedule),
    ``env_amplitude``, ``env_smoothness`` (the two env regularisers).
``ensure_backend(device) -> variant``, ``load_mitsuba(device)``: Mitsuba variant by device
    (``llvm_ad_rgb`` on CPU, ``cuda_ad_rgb`` on CUDA — the CUDA path is untested on CPU-only machines);
    the CPU variant needs a system LLVM >= 19; when the default lookup fails saft finds one and sets
    ``DRJIT_LIBLLVM_PATH``; otherwise ``BackendUnavailableError`` says in one line what to install.

Deviation from the paper (measured)
-----------------------------------
The default image loss is ``"srgb_linearised"``: the sRGB MSE to first order around the target,
(sRGB'(t)·(x − t))². The plain sRGB MSE of a 1-spp Monte Carlo image is biased by the concave sRGB curve
(its expectation is minimised by too-bright renders: in a 30-epoch test the diffuse map drifted to 0.78
grey and the loss rose); the linearised form is quadratic in radiance, so with Mitsuba's decorrelated
primal/adjoint samples its gradient is unbiased at 1 spp. ``loss="srgb"`` restores the paper's form.
(The paper's nvdiffrecmc uses 4 light samples per pixel and a rasterised primary hit, which lowers the
variance but not this bias.)

CPU profile (``cpu_profile``, chosen automatically on CPU by ``profile_for_device``): 100 epochs of 3
random frames, half resolution, 1 spp, plain 128² per-texel maps (lr 0.1, metallic starting at 0.1),
env map fitted at 64×128 (lr 3e-2) and returned upsampled to 256×512, re-renders at 32 spp. Measured with
``benchmarks/bench_appearance.py`` (20 frames of 200×200 px, 16×16 quads): 47 s of CPU time for the fit
(88 s wall on the shared, loaded 2-core machine), held-out PSNR 28.1 dB from 17.6 dB.
In the same short budget the decoder converged more slowly (26.9 vs 28.8 dB at 150×4 epochs), hence texels
on CPU; ``maps="decoder"`` switches back (paper profile default). See ``config.cpu_profile``.

Mitsuba notes: the env-map parameter ``env.data`` carries two wrap-around columns (last, …, first), which
``ClothRenderer.render`` adds; rays start at the near clip plane; Mitsuba has square pixels only (fx must
equal fy within 1 %); an LLVM < 19 aborts the process inside kernel compilation, hence the subprocess probe.
"""

from saft.appearance.config import AppearanceConfig, cpu_profile, paper_profile, profile_for_device
from saft.appearance.fit import (AppearanceResult, fit_appearance, load_appearance, render_appearance,
                                 save_appearance)
from saft.appearance.mitsuba_backend import ensure_backend, load_mitsuba, variant_for_device
from saft.appearance.params import (EnvironmentMap, TexelMaps, TextureDecoder, colour_weight, env_amplitude,
                                    env_smoothness)
from saft.appearance.renderer import ClothRenderer

__all__ = [
    "AppearanceConfig", "AppearanceResult", "ClothRenderer", "EnvironmentMap", "TexelMaps", "TextureDecoder",
    "colour_weight", "cpu_profile", "ensure_backend", "env_amplitude", "env_smoothness", "fit_appearance",
    "load_appearance", "load_mitsuba", "paper_profile", "profile_for_device",
    "render_appearance", "save_appearance", "variant_for_device",
]
