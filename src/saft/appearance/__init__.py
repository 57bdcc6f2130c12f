"""saft.appearance — phase 3: SVBRDF maps and environment light by differentiable ray tracing (Mitsuba 3).

With the motion frozen, a two-sided principled (metallic-roughness) BSDF fed by diffuse/roughness/metallic
maps and a lat-long environment map are fitted to the video by Monte Carlo ray tracing (Mitsuba's ``prb``
integrator, black background, gradients to the maps and the env map only).

API
---
``fit_appearance(vertices_per_frame, triangles, uvs, camera, target_rgb, target_mask, config=None,
device="cpu", progress=None, resume_state=None, checkpoint=None, init_texture=None) -> AppearanceResult``
    vertices_per_frame (F, V, 3); triangles (T, 3); uvs (V, 2) OBJ convention (v up); camera: the OpenCV
    :class:`saft.scene.camera.Camera` of the frames; target_rgb (F, H, W, 3) sRGB in [0, 1]; target_mask
    (F, H, W). ``progress(epoch, epochs, loss)`` after every epoch; ``checkpoint(state)`` every
    ``config.checkpoint_every`` epochs and at the end with a plain dict (epoch, model/env/optimizer state
    dicts, losses, config) that ``resume_state=`` continues from (``torch.save`` it). init_texture: the
    phase-1 texture (sRGB), which ``maps="guided"`` (the CPU profile) starts from.
``AppearanceResult``: diffuse (S, S, 3) linear albedo, roughness (S, S), metallic (S, S), envmap
    (256, 512, 3) linear radiance, losses (per epoch: masked sRGB MSE of the 1-spp renders), config,
    seconds, cpu_seconds, state, materials (maps="guided": per material cluster its area, roughness,
    metallic and whether the video determined it; saved in appearance.json with an "undetermined" note). Maps are numpy float32, row 0 = TOP of the texture image (UV v = 1).
``render_appearance(result, vertices, triangles, uvs, camera, spp=None, device="cpu", seed=0)``
    sRGB re-render(s): (H, W, 3) for (V, 3) vertices, (F, H, W, 3) for (F, V, 3).
``save_appearance(result, out_dir)`` → DIR/material/diffuse.png (sRGB-encoded), roughness.png,
    metallic.png, envmap.exr (linear float, written with Mitsuba's Bitmap: no extra dependency),
    envmap.png (preview), appearance.json; atomically. ``load_appearance(out_dir)`` reads them back.
``AppearanceConfig`` (paper defaults), ``paper_profile()``, ``cpu_profile(base=None)``, ``cuda_profile(base=None)``,
    ``profile_for_device(device, base=None)`` (CPU → cpu_profile, CUDA → cuda_profile).
``ClothRenderer(triangles, uvs, camera, device, max_depth=2, map_shape, env_shape)``: ``set_vertices(v)``
    per frame (updates positions + normals through ``mi.traverse``, no rebuild), ``render(diffuse,
    roughness, metallic, env, spp, seed)`` → linear (H, W, 3) torch tensor, differentiable in the inputs.
``GuidedMaps`` (guided: the phase-1 texture with its shading divided out by a coarse gain grid, roughness
    and metallic constant per colour cluster, metallic sparsity prior, a learnt share of the texture's fine detail), ``cluster_evidence``
    (evidence: is a cluster's material determined by the video?), ``PyramidEnvironmentMap`` (exp of a
    pyramid of log-radiance grids, fitted coarse to fine),
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

Profiles (``config``): ``profile_for_device`` picks ``cpu_profile`` on a CPU and ``cuda_profile`` on CUDA;
``appearance.profile = "paper"`` keeps the paper's own settings (decoder maps from a grey start). Both
automatic profiles use the parametrisation chosen on the ground-truth metrics of the appearance benchmark
(``benchmarks/bench_appearance.py``, BENCHMARKS.md "Appearance against ground truth"; issue 28):
``maps="guided"`` (512² maps from the phase-1 texture, blurred inside colour clusters, with its shading
divided out by an 8×8 gain grid; roughness and metallic constant per cluster; metallic sparsity; the
per-cluster evidence test, which sets what the video does not determine to matte and says so in
appearance.json), a log-radiance pyramid env map and learning rates decaying to a tenth. The CPU profile
fits 150 epochs of 3 frames at half resolution; the CUDA profile the paper's budget (2000 epochs of every
frame at full resolution), unmeasured on a GPU. The previous CPU profile (128² free texels, chosen by
re-render PSNR on fitted frames) was worse than no phase 3 at all against the true maps (issue 28).

Mitsuba notes: the env-map parameter ``env.data`` carries two wrap-around columns (last, …, first), which
``ClothRenderer.render`` adds; rays start at the near clip plane; Mitsuba has square pixels only (fx must
equal fy within 1 %); an LLVM < 19 aborts the process inside kernel compilation, hence the subprocess probe.
"""

from saft.appearance.config import AppearanceConfig, cpu_profile, cuda_profile, paper_profile, profile_for_device
from saft.appearance.evidence import cluster_evidence
from saft.appearance.fit import (AppearanceResult, fit_appearance, load_appearance, render_appearance,
                                 save_appearance)
from saft.appearance.guided import GuidedMaps
from saft.appearance.mitsuba_backend import ensure_backend, load_mitsuba, variant_for_device
from saft.appearance.params import (EnvironmentMap, PyramidEnvironmentMap, TexelMaps, TextureDecoder, colour_weight,
                                    env_amplitude, env_smoothness)
from saft.appearance.renderer import ClothRenderer

__all__ = [
    "AppearanceConfig", "AppearanceResult", "ClothRenderer", "EnvironmentMap", "GuidedMaps", "PyramidEnvironmentMap",
    "TexelMaps", "TextureDecoder", "cluster_evidence", "colour_weight", "cpu_profile", "cuda_profile", "ensure_backend", "env_amplitude", "env_smoothness", "fit_appearance",
    "load_appearance", "load_mitsuba", "paper_profile", "profile_for_device",
    "render_appearance", "save_appearance", "variant_for_device",
]
