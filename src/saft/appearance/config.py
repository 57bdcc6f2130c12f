"""AppearanceConfig: the phase-3 settings with the paper's defaults, and the automatic CPU profile."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Literal

from saft.config_io import from_dict
from saft.errors import SaftInputError


@dataclass
class AppearanceConfig:
    """Settings of the appearance phase. Defaults are the paper's (REFERENCE.md "Appearance estimation")."""

    enabled: bool = True
    profile: Literal["paper", "cpu", "cuda", "auto"] = "paper"  # informational, stated in the output; "auto" is
    # resolved before a run (saft.reconstruct.config.load_saft_config, appearance.profile_for_device)
    epochs: int = 2000
    # colour schedule of the environment map: grey 800, blend 400, colour 800 of 2000 epochs
    grey_fraction: float = 0.4
    blend_fraction: float = 0.2
    # texture parametrisation: "decoder" (paper), "texels" (plain per-texel maps) or "guided" (the phase-1
    # texture times a coarse log-gain grid; roughness/metallic constant per colour cluster: appearance.guided)
    maps: Literal["decoder", "texels", "guided"] = "decoder"
    gain_grid: int = 16                  # maps="guided": side of the diffuse log-gain grid
    # maps="guided": what divides the frame-0 shading out of the texture: "gain" (a free colour log-gain
    # grid) or "irradiance" (π·T / E0, E0 the frame-0 irradiance from the fitted env map, times a grey
    # log-gain grid: appearance.irradiance; the profiles' choice, BENCHMARKS "A physically divided diffuse")
    diffuse_shading: Literal["gain", "irradiance"] = "gain"
    # diffuse_shading="irradiance": > 1: this many frames (evenly spaced, frame 0 among them) measure frame
    # 0's specular in the texture, which is taken off it before the division: frame 0 beyond the per-texel
    # median of the frames divided by their own irradiance under the fitted env map, re-measured every
    # epoch (appearance.frame_specular); 0 = nothing taken off; the profiles' 32
    frame_specular: int = 0
    clusters: int = 6                    # maps="guided": material clusters (k-means on the texture's colours)
    texture_smoothing: float = 0.0       # maps="guided": σ (texels) of the blur inside each cluster
    # maps="guided": a frame teaches the per-cluster detail share only if it repeats at least this fraction
    # of the texture's detail that frames 1-2 repeat (appearance.detail: its motion lines the pattern up);
    # 0 = every frame teaches it. The profiles' 0.5, with saft's motion (bench_appearance, 320x240, 32
    # frames): plaid diffuse 19.72 -> 20.69 dB, relit 28.75 / 30.04 -> 30.03 / 31.33 dB (frames 12-31 left
    # out); lame within 0.005 dB (frames 6-8 left out); cotton, print, satin and every fabric's true motion
    # leave no frame out (the same fit). 0.75: plaid 20.76, 30.18 / 31.50, set on plaid alone, not taken
    # (BENCHMARKS.md, issue 28, "Which frames may teach the detail share")
    detail_trust: float = 0.0
    # >= 2: before the fit, the phase-1 texture (fitted on frame 0 alone) is refitted on frames 0 … N−1
    # through their meshes with the shape phase's rasteriser, each frame with its own smooth gain (frame 0's
    # fixed at 1, so the texture keeps frame 0's shading) and its mesh registered by a grid of image-plane
    # shifts (appearance.texture_frames: frame noise averaged, sub-pixel shifts resolving detail finer than
    # one frame's pixels); 0 = off (phase 1's texture as it is)
    texture_frames: int = 0
    # > 0: a per-frame correction of the shading normals is learnt with the maps (appearance.normals): a
    # tangent offset on a normal_grid × normal_grid bilinear lattice over the UV square, at normal_keys
    # keyframes in time (0 = one per frame) linearly interpolated, zero at frame 0; rate lr_normals, and
    # lambda_normals times the mean squared offset pulls it towards the meshes' own normals. For saft's
    # own motion, whose normals are off by 5-20° (BENCHMARKS "Highlights on a wrong shape"); 0 = off. Left off
    # where the clip starts curved in motion (saft.scene.motion.starts_curved_in_motion: cut mid-motion): there
    # it lost on the cotton and the lamé at both seeds. On a flat cloth already in a breeze (Newton's clips,
    # seed 0) it is on: satin roughness 0.554 -> 0.537, plaid 0.281 -> 0.195, print 0.338 -> 0.313, cotton and
    # lamé level (BENCHMARKS.md, "Fourteenth session").
    normal_grid: int = 0
    normal_keys: int = 8
    lr_normals: float = 0.01
    lambda_normals: float = 1e-3
    lambda_metallic_l1: float = 0.0      # maps="guided": area-weighted mean metallic (sparsity prior)
    # maps="guided": each cluster gets a bright metal colour of its own (brightest channel >= 0.5, as any
    # real metal's F0), the base colour (1 − m)·diffuse + m·colour (appearance.metal: the lamé's gold threads,
    # whose frame-0 radiance divided as a diffuse is darker than any metal); such a cluster's metallic moves
    # metal_rate times as fast and is priced by lambda_metal_blend × area × m(1 − m) (metal or not) instead
    # of the sparsity prior. Off (BENCHMARKS "Metals are bright"; issue 28)
    metal_colour: bool = False
    lambda_metal_blend: float = 0.01
    metal_rate: float = 3.0
    # metal_colour: > 0: only the clusters whose highlights over the frames keep their own colour (score >=
    # metal_gate, appearance.metal_gate: a metal's highlight has its F0's colour, a dielectric's the light's)
    # get a metal colour; the others keep the default (no colour, the sparsity prior). 0 = every cluster
    metal_gate: float = 0.0
    # metal_colour: > 0: after the fit, each metal-coloured cluster whose metallic ended in [0.05, 0.95] is
    # refitted this many epochs twice from the fitted state, its metallic pinned at 1 and at 0, the maps and
    # the env map (normals as fitted) at the fit's rates of mid-decay (lr_texels, lr_env × √lr_final_factor), on
    # all frames but 8 evenly spaced ones; where the metal's loss on those 8 is lower than the dielectric's
    # the cluster becomes metal, otherwise the fit is left as it was (appearance.metal_decide: a thread is
    # metal or not; the lamé's ended half metal); 0 = off. 40 in the profiles (with metal_decide_ramp below).
    # 30, pinned at once: saft's lamé at seed 0 metallic 0.150 -> 0.055, relit unseen 23.57 -> 26.09 dB, true
    # motion 0.054 -> 0.012; at seed 1 the metal lost the test and the fit stayed as it was; nothing decided on
    # the other fabrics (BENCHMARKS.md "The lamé's gold threads as metal…").
    # Lost and removed: the metal clusters started at metallic 0.5, and the metal's refit from a dimmed light.
    metal_decide: int = 0
    # metal_decide > 0: > 1: each refit moves the cluster's metallic on a straight line from its fitted value
    # to the pin over this many of its epochs, the light and the maps following (appearance.metal_decide:
    # pinned at once, a metal starts at 15-30x the fit's held-out loss under the light fitted for a half
    # metal and 30 epochs do not bring it back: the lamé's threads at seed 1); 0 = pinned at once. 20 in the
    # profiles, with metal_decide = 40 and follow: the lamé's threads found at seed 1 too (metallic
    # 0.167 -> 0.016, relit +2.8 / +2.7 dB), at seed 0 relit -0.35 / -0.43 dB; 30 / 15 lost seed 1 (BENCHMARKS.md,
    # "The lamé's threads at seed 1…"). Lost and removed: the refits' rates decaying after the pin (diffuse
    # -0.20 / -0.38 dB)
    metal_decide_ramp: int = 0
    # metal_decide > 0: once a cluster has become metal, the metal-coloured clusters the fit left below
    # metallic 0.05 are decided too (a thread's rim, split from its core by the colour clusters: the lamé's at
    # seed 1, metallic 0.002 after the fit); off: only [0.05, 0.95]. A cloth without a half metal is never
    # refitted. Deciding every metal-coloured cluster from the start lost: the print's 4 % cluster made metal,
    # relit −6.5 dB (BENCHMARKS.md, "The lamé's threads at seed 1…")
    metal_decide_follow: bool = False
    # metal_decide > 0 and this > 0: the metal-coloured clusters the fit left below metallic 0.05 but glossy
    # (roughness <= this) are decided from the start too, like the half metals (a glossy highlight of the cluster's
    # own colour is a metal's or a coloured dielectric's, which the decision's test tells apart; Newton's lamé: its
    # threads show their highlights in a late gust only, fall to metallic 0.002-0.008 within 15 epochs and end a
    # glossy dielectric, roughness 0.12-0.35, so no cluster was ever decided; every other metal-coloured cluster of
    # the five fabrics on both cloths ended rough, >= 0.72). Every cluster decided from below 0.05 starts its metal
    # refit with the colour of its highlights (metal_gate.highlight_hue), not the metal colour the fit left: at
    # metallic 0.002 Adam drifts it freely (the Newton threads' from the gold they start at, (0.80, 0.57, 0.24), to
    # (0.74, 0.47, 0.52) on saft's motion, (0.89, 0.89, 0.84) on the true one); 0 = off.
    # Lost and removed: the metal also judged against the fit as it stands, not only the dielectric's refit
    # (metal_decide_strict): it threw away the lamé's threads that beat the dielectric (saft's cloth at seed 1,
    # Newton's at both seeds; BENCHMARKS.md "Newton's lamé: where the gold threads are lost…")
    metal_decide_glossy: float = 0.0
    # maps="guided": mean squared colour of the log-gain grid (each cell's channels minus their mean), a
    # prior that ties the gain's colour to grey so the light's colour goes to the env map (0 = off)
    lambda_gain_chroma: float = 0.0
    # maps="guided": a cluster whose fitted material lowers the loss by less than this (relative) against
    # matte is set to matte and reported undetermined (appearance.evidence); 0 = no test
    evidence_threshold: float = 0.0
    evidence_spp: int = 4
    # evidence_threshold > 0: an undetermined cluster gets roughness 1 ("matte", the texture-only assumption)
    # or ("band") the middle of the roughness range its frames do not rule out (appearance.evidence). Off:
    # "band" lowers the roughness MAE wherever a cluster is undetermined (print 0.170 -> 0.137 and 0.135 ->
    # 0.105, lamé 0.200 -> 0.196 and 0.214 -> 0.165 at seeds 0 / 1, saft's motion) but the relit views lose
    # 0.05-0.38 dB (BENCHMARKS.md, "What the frames allow for an undetermined cluster's roughness")
    undetermined_roughness: Literal["matte", "band"] = "matte"
    tile_size: int = 128                 # decoder tile side (4·2^k)
    num_tiles: int = 16                  # tiles on a square grid (16 → 4×4)
    tile_overlap: int = 10               # → maps of 4·(128−10) = 472 px
    latent_channels: int = 512           # fixed random latent latent_channels×4×4
    texel_size: int = 472                # side of the per-texel maps (maps="texels" or "guided")
    min_roughness: float = 1e-3
    init_diffuse: float = 0.5
    init_roughness: float = 0.5
    init_metallic: float = 0.5
    lr_decoder: float = 2e-4
    betas_decoder: tuple[float, float] = (0.99, 0.9999)
    lr_texels: float = 2e-2
    # every learning rate decays exponentially to this factor at the last epoch (1 = constant, the paper):
    # with 1-spp gradients a constant rate leaves the parameters jittering by about one step at the end
    lr_final_factor: float = 1.0
    # environment map (lat-long, linear radiance): fitted at env_height×env_width, returned (bilinearly
    # upsampled if smaller) at env_output_height×env_output_width
    env_height: int = 256
    env_width: int = 512
    env_output_height: int = 256
    env_output_width: int = 512
    env_init: float = 0.5
    env_min: float = 0.01
    env_levels: int = 1                  # 1: one linear grid (paper); > 1: exp of a pyramid of log grids
    lr_env: float = 1e-2
    betas_env: tuple[float, float] = (0.9, 0.999)
    lambda_env_l1: float = 1e-5          # L1 amplitude of the env map
    lambda_env_smooth: float = 5e-5      # finite-difference smoothness of the env map
    # image loss: "srgb" (the paper's sRGB MSE) or "srgb_linearised" (its first-order form around the
    # target, unbiased under 1-spp Monte Carlo noise; see fit.masked_linearised_srgb_mse)
    loss: Literal["srgb", "srgb_linearised"] = "srgb_linearised"
    # loss="srgb_linearised": > 0: the loss is (1 − loss_blur_weight) times the per-pixel one plus
    # loss_blur_weight times the same residual blurred by a Gaussian of loss_blur pixels (at the fit's
    # resolution; appearance.tolerant), so that a highlight a few pixels off (saft's own motion is a
    # centimetre off) costs little; 0 = off
    loss_blur: float = 0.0
    loss_blur_weight: float = 0.5
    # rendering
    spp: int = 1                         # samples per pixel while fitting
    max_depth: int = 2                   # 2 = direct lighting with shadows (emitter + BSDF sampling, MIS)
    render_spp: int = 64                 # samples per pixel of the final re-renders / novel view
    image_scale: float = 1.0             # fit at this fraction of the input resolution
    frames_per_epoch: int = 0            # 0 = every frame in every epoch; else a random mini-batch
    seed: int = 0
    checkpoint_every: int = 50           # epochs between checkpoint callbacks

    def validate(self) -> None:
        def bad(key, why):
            raise SaftInputError(f"appearance.{key}", why)

        if self.epochs < 1:
            bad("epochs", "must be >= 1")
        if not (0 < self.lr_final_factor <= 1):
            bad("lr_final_factor", "must lie in (0, 1]")
        if self.undetermined_roughness not in ("matte", "band"):
            bad("undetermined_roughness", "must be 'matte' or 'band'")
        if self.maps not in ("decoder", "texels", "guided"):
            bad("maps", "must be 'decoder', 'texels' or 'guided'")
        if self.diffuse_shading not in ("gain", "irradiance"):
            bad("diffuse_shading", "must be 'gain' or 'irradiance'")
        if self.frame_specular < 0 or self.frame_specular == 1:
            bad("frame_specular", "must be 0 (off) or >= 2 frames")
        if self.normal_grid < 0 or self.normal_keys < 0 or self.lr_normals < 0 or self.lambda_normals < 0:
            bad("normal_grid", "normal_grid, normal_keys, lr_normals and lambda_normals must be >= 0")
        if self.metal_rate <= 0 or self.lambda_metal_blend < 0 or not (0 <= self.metal_gate <= 1):
            bad("metal_rate", "metal_rate must be > 0, lambda_metal_blend >= 0 and metal_gate lie in [0, 1]")
        if self.metal_decide < 0 or self.metal_decide_ramp < 0:
            bad("metal_decide", "metal_decide and metal_decide_ramp must be >= 0 epochs (0 = off)")
        if not (0 <= self.metal_decide_glossy <= 1):
            bad("metal_decide_glossy", "must lie in [0, 1] (a roughness; 0 = off)")
        if self.gain_grid < 1 or self.clusters < 1:
            bad("clusters", "gain_grid and clusters must be >= 1")
        if self.env_levels < 1 or (self.env_height >> (self.env_levels - 1)) < 1:
            bad("env_levels", "must be >= 1 and leave at least one row at the coarsest level")
        if not (0 <= self.grey_fraction and 0 <= self.blend_fraction and self.grey_fraction + self.blend_fraction <= 1):
            bad("grey_fraction", "grey_fraction + blend_fraction must lie in [0, 1]")
        if self.loss not in ("srgb", "srgb_linearised"):
            bad("loss", "must be 'srgb' or 'srgb_linearised'")
        if self.loss_blur < 0 or not (0 <= self.loss_blur_weight <= 1):
            bad("loss_blur", "loss_blur must be >= 0 and loss_blur_weight lie in [0, 1]")
        if self.spp < 1 or self.render_spp < 1:
            bad("spp", "must be >= 1")
        if not (0 < self.image_scale <= 1):
            bad("image_scale", "must lie in (0, 1]")
        if self.texture_frames < 0 or self.texture_frames == 1:
            bad("texture_frames", "must be 0 (off) or >= 2 frames")
        if not (0 <= self.detail_trust <= 1):
            bad("detail_trust", "must lie in [0, 1]")
        if self.frames_per_epoch < 0:
            bad("frames_per_epoch", "must be >= 0")
        if self.env_height < 2 or self.env_width < 2:
            bad("env_height", "env map too small")
        if self.max_depth < 2:
            bad("max_depth", "must be >= 2 (1 shows only the hidden background)")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict, where: str = "appearance config") -> "AppearanceConfig":
        """Strictly, as every saft config (saft.config_io.from_dict): unknown keys and wrong types are errors."""
        return from_dict(AppearanceConfig, d, where, "appearance.")


def paper_profile() -> AppearanceConfig:
    """The paper's settings (2000 epochs, 472² decoder maps, 256×512 env map, 1 spp, all frames)."""
    return AppearanceConfig()


# The parametrisation and priors chosen on the appearance benchmark's ground-truth metrics (issue 28;
# benchmarks/bench_appearance.py, BENCHMARKS.md "Appearance against ground truth"), shared by the CPU and
# CUDA profiles: maps from the phase-1 texture (blurred inside colour clusters, divided by its frame-0
# irradiance under the fitted env map times a grey 8×8 gain grid, roughness / metallic per cluster),
# metallic sparsity, the per-cluster evidence test, a log-radiance pyramid env map (64×128 over 5 levels),
# learning rates decaying to a tenth; the detail share learnt only from the frames whose motion lines the
# texture's weave up (detail_trust); frame 0's moving specular, measured from 32 frames, taken off the texture
# before the division (frame_specular: on a billowed frame 0 the satin's roughness MAE 0.363 -> 0.175 and
# metallic 0.044 -> 0, the other fabrics and the flat frame 0 unchanged within the fits' seed noise; BENCHMARKS
# "Frame 0's specular measured from the frames"); the phase-1 texture refitted on the first 8 trusted frames
# (texture_frames: the plaid 20.8 -> 23.2-24.0 dB diffuse, relit +1.7 ... +2.6 dB, cells beating texture only
# 15 -> 19, 17 -> 19, Newton's cloth 15 -> 18; the print's roughness on Newton's cloth 0.04 worse at both seeds;
# BENCHMARKS "The phase-1 texture refitted on several frames"); the shading normals corrected per frame on a 4×4
# lattice at 16 keys (normal_grid: saft's satin roughness 0.283 -> 0.039 and 0.275 -> 0.058, relit +6 to +8 dB,
# seeds 0 / 1) and a bright metal colour for the clusters whose highlights keep their colour (metal_colour,
# metal_gate: the lamé +3.2 / +1.9 dB diffuse, relit +1.3 to +2.6 dB; BENCHMARKS "Twelfth session's defaults");
# the metal-coloured clusters the fit left a glossy dielectric decided too, the metal judged against the
# dielectric's refit only (metal_decide_glossy 0.5, no longer also against the fit as it stands: Newton's lamé
# roughness MAE 0.220 -> 0.068 / 0.190 -> 0.056, metallic 0.178 -> 0.027 / 0.041, relit +1.6 to +2.4 dB; saft's
# lamé at seed 1 0.158 -> 0.046, relit +2.8 / +3.3 dB; the other fabrics equal; BENCHMARKS "Newton's lamé: where
# the gold threads…").
GUIDED = dict(maps="guided", texel_size=512, gain_grid=8, clusters=6, texture_smoothing=4.0, lambda_metallic_l1=0.01,
              normal_grid=4, normal_keys=16, lr_normals=0.03, lambda_normals=0.03, metal_colour=True, metal_gate=0.5,
              metal_decide=40, metal_decide_ramp=20, metal_decide_follow=True, metal_decide_glossy=0.5,
              detail_trust=0.5, diffuse_shading="irradiance", frame_specular=32, texture_frames=8,
              evidence_threshold=0.01, lr_texels=0.1, lr_final_factor=0.1, init_roughness=0.6, init_metallic=0.1,
              env_levels=5, lr_env=0.05, env_height=64, env_width=128)


def cpu_profile(base: AppearanceConfig | None = None) -> AppearanceConfig:
    """The automatic CPU profile, chosen on the ground-truth metrics of bench_appearance.py (see GUIDED):
    150 epochs of 3 random frames at half resolution (160×120 for a 320×240 video), 1 spp, 512² maps, the
    env map fitted at 64×128 (5 pyramid levels; at 32×64 over 4 the roughness MAE was higher on cotton,
    print and satin) and returned upsampled to 256×512, re-renders at 32 spp.
    The decoder's values below serve maps="decoder" only.
    """
    base = base or AppearanceConfig()
    return replace(
        base,
        profile="cpu",
        epochs=150,
        frames_per_epoch=3,
        image_scale=0.5,
        **GUIDED,
        tile_size=32,
        tile_overlap=4,
        latent_channels=128,
        lr_decoder=5e-3,
        betas_decoder=(0.9, 0.999),
        render_spp=32,
        checkpoint_every=25,
    )


def cuda_profile(base: AppearanceConfig | None = None) -> AppearanceConfig:
    """The automatic CUDA profile: the paper's budget (2000 epochs of every frame at full resolution, 1 spp,
    256×512 output env map) with the parametrisation and priors measured on the CPU (GUIDED). Not measured
    on a GPU (Mitsuba's CUDA variant has not run
    in this project); ``appearance.profile = "paper"`` gives the paper's own settings.
    """
    base = base or AppearanceConfig()
    return replace(base, profile="cuda", epochs=2000, frames_per_epoch=0, image_scale=1.0, **GUIDED)


def profile_for_device(device, base: AppearanceConfig | None = None) -> AppearanceConfig:
    """The CPU profile on a CPU device, the CUDA profile on any other (both on top of `base`)."""
    kind = getattr(device, "type", None) or str(device or "cpu").split(":")[0]
    if kind == "cpu":
        return cpu_profile(base)
    return cuda_profile(base)

