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
    profile: Literal["paper", "cpu", "auto"] = "paper"  # informational, stated in the output; "auto" is
    # resolved before a run (saft.reconstruct.config.load_saft_config, appearance.profile_for_device)
    epochs: int = 2000
    # colour schedule of the environment map: grey 800, blend 400, colour 800 of 2000 epochs
    grey_fraction: float = 0.4
    blend_fraction: float = 0.2
    # texture parametrisation: "decoder" (paper) or "texels" (plain per-texel maps)
    maps: Literal["decoder", "texels"] = "decoder"
    tile_size: int = 128                 # decoder tile side (4·2^k)
    num_tiles: int = 16                  # tiles on a square grid (16 → 4×4)
    tile_overlap: int = 10               # → maps of 4·(128−10) = 472 px
    latent_channels: int = 512           # fixed random latent latent_channels×4×4
    texel_size: int = 472                # side of the per-texel maps (maps="texels")
    min_roughness: float = 1e-3
    init_diffuse: float = 0.5
    init_roughness: float = 0.5
    init_metallic: float = 0.5
    lr_decoder: float = 2e-4
    betas_decoder: tuple[float, float] = (0.99, 0.9999)
    lr_texels: float = 2e-2
    # environment map (lat-long, linear radiance): fitted at env_height×env_width, returned (bilinearly
    # upsampled if smaller) at env_output_height×env_output_width
    env_height: int = 256
    env_width: int = 512
    env_output_height: int = 256
    env_output_width: int = 512
    env_init: float = 0.5
    env_min: float = 0.01
    lr_env: float = 1e-2
    betas_env: tuple[float, float] = (0.9, 0.999)
    lambda_env_l1: float = 1e-5          # L1 amplitude of the env map
    lambda_env_smooth: float = 5e-5      # finite-difference smoothness of the env map
    # image loss: "srgb" (the paper's sRGB MSE) or "srgb_linearised" (its first-order form around the
    # target, unbiased under 1-spp Monte Carlo noise; see fit.masked_linearised_srgb_mse)
    loss: Literal["srgb", "srgb_linearised"] = "srgb_linearised"
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
        if self.maps not in ("decoder", "texels"):
            bad("maps", "must be 'decoder' or 'texels'")
        if not (0 <= self.grey_fraction and 0 <= self.blend_fraction and self.grey_fraction + self.blend_fraction <= 1):
            bad("grey_fraction", "grey_fraction + blend_fraction must lie in [0, 1]")
        if self.loss not in ("srgb", "srgb_linearised"):
            bad("loss", "must be 'srgb' or 'srgb_linearised'")
        if self.spp < 1 or self.render_spp < 1:
            bad("spp", "must be >= 1")
        if not (0 < self.image_scale <= 1):
            bad("image_scale", "must lie in (0, 1]")
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


def cpu_profile(base: AppearanceConfig | None = None) -> AppearanceConfig:
    """The automatic CPU profile, chosen by measurement on the shared 2-core CPU (bench_appearance.py:
    20 frames of 200×200 px, 16×16-quad sheet, 15 frames fitted, 5 held out).

    * 100 epochs of 3 random frames each, at half resolution (100×100 px), 1 spp: 47 s of CPU time for
      the fit (88 s wall with 3–4 other jobs on the 2 cores); held-out PSNR 28.1 dB (grey start 17.6 dB).
      (With a 256×512 env map: 27.6 dB in 89 s CPU; 150 epochs × 4 frames: 28.8 dB in ~2× the time.)
    * Plain per-texel maps (128², lr 0.1) instead of the decoder: in the same 150×4 budget the decoder
      (32-px tiles, latent 128, lr 5e-3) reached 26.9 dB against 28.8 dB for texels, and ran slower; the
      decoder stays available (maps="decoder", using the tile/latent/lr values below) and is the paper
      profile's default.
    * Metallic starts at 0.1 instead of 0.5 (cloth is mostly dielectric; a short schedule does not recover
      from a half-metal start as well).
    * The env map is fitted at 64×128 and returned upsampled to 256×512: at 1 spp over only ~300 frame
      renders, a 256×512 map receives sparse gradients per texel and Adam turns them into salt-and-pepper
      noise; the coarser grid pools them.
    """
    base = base or AppearanceConfig()
    return replace(
        base,
        profile="cpu",
        epochs=100,
        frames_per_epoch=3,
        image_scale=0.5,
        maps="texels",
        texel_size=128,
        lr_texels=0.1,
        init_metallic=0.1,
        tile_size=32,
        tile_overlap=4,
        latent_channels=128,
        lr_decoder=5e-3,
        betas_decoder=(0.9, 0.999),
        lr_env=3e-2,
        env_height=64,
        env_width=128,
        render_spp=32,
        checkpoint_every=25,
    )


def profile_for_device(device, base: AppearanceConfig | None = None) -> AppearanceConfig:
    """The CPU profile on a CPU device, the paper's settings (or `base`) on CUDA."""
    kind = getattr(device, "type", None) or str(device or "cpu").split(":")[0]
    if kind == "cpu":
        return cpu_profile(base)
    return base or paper_profile()

