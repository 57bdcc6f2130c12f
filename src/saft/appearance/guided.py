"""Texture-guided material maps (``maps="guided"``): a well-posed parameterisation for few, noisy frames.

The data of a short video cannot tell every material from every light, so the unknowns are cut down to
what it can determine (issue 28):

* diffuse = clamp((T_s + a·(T − T_s)) · exp(G↑), 0, 1): T is the phase-1 texture (linearised, resampled to
  S×S: the sharp detail), T_s the same blurred inside each material cluster (its pixel noise averaged
  away, but also any pattern finer than the blur, such as a weave), a ∈ (0, 1) per cluster a learnt share
  of the removed detail (the frames decide: noise of frame 0 does not repeat in other frames), G a coarse g×g×3 log-gain grid, bilinearly upsampled (G↑), that divides out the shading and
  the light's colour baked into T at frame 0 (shading varies at the scale of the folds, not of the texels);
* roughness and metallic are piecewise constant over K material clusters: k-means (scipy) on the
  texture's colours, since a thread of one colour is one material. Each cluster has one roughness and one
  metallic (sigmoid of a free logit): 2K numbers estimated from every pixel of every frame instead of
  2·S² noisy texels;
* ``metallic_l1()``: the area-weighted mean metallic, a sparsity prior that keeps clusters dielectric
  unless the data insists;
* ``gain_chroma()``: the mean squared colour of the log-gain grid (a grey gain costs nothing), a prior
  against the gain × light colour trade-off that makes rough fabrics glossy (issue 28).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as Fnn
from scipy.cluster.vq import kmeans2
from scipy.ndimage import gaussian_filter
from torch import nn

from saft.appearance.metal import MetalColour, metal_blend
from saft.appearance.params import logit


def _merge_close(centres: np.ndarray, distance: float) -> np.ndarray:
    """Greedily merge cluster centres closer than `distance` (k-means splits one noisy colour into several
    clusters when asked for more than there are; their materials would then be fitted apart from noise)."""
    groups = [[c] for c in centres]
    merged = True
    while merged and len(groups) > 1:
        merged = False
        means = np.array([np.mean(g, axis=0) for g in groups])
        d = np.linalg.norm(means[:, None] - means[None], axis=-1) + np.eye(len(groups)) * 1e9
        i, j = np.unravel_index(d.argmin(), d.shape)
        if d[i, j] < distance:
            groups[min(i, j)] += groups.pop(max(i, j))
            merged = True
    return np.array([np.mean(g, axis=0) for g in groups])


def material_clusters(texture_linear: np.ndarray, k: int, seed: int = 0, sample: int = 20000,
                      merge: float = 0.05, min_share: float = 0.03) -> np.ndarray:
    """(S, S) int labels in [0, k'): k-means on the sRGB-encoded colours (perceptually even) of the texture
    blurred by σ = S/128 texels (the phase-1 texture carries pixel noise, which would speckle the labels),
    fitted on a random sample of texels; centres closer than `merge` are merged, clusters of less than
    `min_share` of the texels (the blends along colour edges) are given to their nearest neighbours and
    clusters that end up empty are dropped (k' <= k)."""
    tex = np.asarray(texture_linear, dtype=np.float64)
    sigma = tex.shape[0] / 128
    feats = gaussian_filter(np.clip(tex, 0, 1) ** (1 / 2.2), sigma=(sigma, sigma, 0), mode="nearest")
    flat = feats.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    pick = flat[rng.choice(len(flat), min(sample, len(flat)), replace=False)]
    centres, _ = kmeans2(pick, k, seed=seed, minit="++")
    centres = _merge_close(centres, merge)
    d = ((flat[:, None, :] - centres[None]) ** 2).sum(-1)
    share = np.bincount(d.argmin(1), minlength=len(centres)) / len(flat)
    if (share >= min_share).any():  # the blend at a colour edge is no material of its own
        d = d[:, share >= min_share]
    labels = d.argmin(1)
    _, labels = np.unique(labels, return_inverse=True)
    return labels.reshape(tex.shape[:2]).astype(np.int64)


def smooth_within_clusters(texture: np.ndarray, labels: np.ndarray, sigma: float,
                           weight: np.ndarray | None = None) -> np.ndarray:
    """The texture blurred by σ texels inside each cluster only (normalised convolution, Σ_k blur(T·M_k) /
    blur(M_k) on M_k): the phase-1 texture's pixel noise is averaged away while the edges between colours
    (stripes, threads, print) stay sharp. weight (S, S) bool, optional: only these texels enter the blur
    (M_k·weight; appearance.detail: the texels a frame sees), and the rest of the output is 0."""
    if sigma <= 0:
        return texture
    out = np.zeros_like(texture)
    for k in range(int(labels.max()) + 1):
        m = ((labels == k) & (True if weight is None else weight)).astype(np.float64)
        num = gaussian_filter(texture * m[..., None], sigma=(sigma, sigma, 0), mode="nearest")
        den = gaussian_filter(m, sigma=sigma, mode="nearest")[..., None]
        out += m[..., None] * num / np.maximum(den, 1e-6)
    return out.astype(texture.dtype)


class GuidedMaps(nn.Module):
    """Maps of S×S texels from the phase-1 texture (module docstring). texture: (St, St, 3) LINEAR."""

    def __init__(self, texture_linear: np.ndarray, size: int = 512, gain_grid: int = 16, clusters: int = 6,
                 min_roughness: float = 1e-3, init_roughness: float = 0.5, init_metallic: float = 0.1, seed: int = 0,
                 smoothing: float = 0.0):
        super().__init__()
        tex = torch.as_tensor(np.asarray(texture_linear, dtype=np.float32)[..., :3]).permute(2, 0, 1)[None]
        mode = "area" if tex.shape[-1] > size else "bilinear"
        tex = Fnn.interpolate(tex, size=(size, size), mode=mode, **({} if mode == "area" else {"align_corners": False}))
        tex = tex[0].permute(1, 2, 0).clamp(1e-3, 1.0).numpy()
        labels = material_clusters(tex, clusters, seed)
        self.register_buffer("texture", torch.as_tensor(smooth_within_clusters(tex, labels, smoothing)))
        self.register_buffer("detail", torch.as_tensor(tex) - self.texture)   # what the smoothing removed
        labels = torch.as_tensor(labels)
        k = int(labels.max()) + 1
        onehot = Fnn.one_hot(labels, k).permute(2, 0, 1).to(torch.float32)  # (k, S, S)
        self.register_buffer("members", onehot)
        self.register_buffer("area", onehot.mean(dim=(1, 2)))
        self.min_roughness = min_roughness
        self.gain = nn.Parameter(torch.zeros(1, 3, gain_grid, gain_grid))
        self.rough_logit = nn.Parameter(torch.full((k,), logit(init_roughness)))
        self.metal_logit = nn.Parameter(torch.full((k,), logit(init_metallic)))
        # metallic = sigmoid(metal_logit · metal_scale): a scale > 1 moves a cluster's metallic that many times
        # faster under Adam (use_metal_colour's rate); 1 for every cluster otherwise
        self.register_buffer("metal_scale", torch.ones(k))
        self.metal = None   # appearance.metal.MetalColour once use_metal_colour() is called
        # per cluster, how much of the removed detail comes back (sigmoid; starts at one half): the frames
        # decide whether it was the texture's noise (it does not repeat in other frames) or a real pattern
        self.detail_logit = nn.Parameter(torch.zeros(k))

    @property
    def size(self) -> int:
        return int(self.texture.shape[0])

    @property
    def num_clusters(self) -> int:
        return int(self.members.shape[0])

    def cluster_values(self) -> dict[str, torch.Tensor]:
        return {"roughness": torch.sigmoid(self.rough_logit).clamp_min(self.min_roughness),
                "metallic": torch.sigmoid(self.metal_logit * self.metal_scale)}

    def detailed_texture(self) -> torch.Tensor:
        """(S, S, 3) T_s + a·(T − T_s): the blurred texture with each cluster's learnt share of its detail."""
        detail = torch.einsum("k,khw->hw", torch.sigmoid(self.detail_logit), self.members)
        return self.texture + self.detail * detail[..., None]

    def material_maps(self) -> dict[str, torch.Tensor]:
        """Roughness and metallic (S, S), constant per cluster."""
        vals = self.cluster_values()
        return {"roughness": torch.einsum("k,khw->hw", vals["roughness"], self.members),
                "metallic": torch.einsum("k,khw->hw", vals["metallic"], self.members)}

    def use_metal_colour(self, rate: float = 1.0, allowed=None) -> None:
        """Give each cluster (or the `allowed` (K,) bool ones) a bright metal colour of its own
        (appearance.metal), its metallic moving `rate` times as fast."""
        k = self.num_clusters
        allowed = np.ones(k, bool) if allowed is None else np.asarray(allowed, bool)
        mean = (torch.einsum("khw,hwc->kc", self.members, self.texture) / self.members.sum((1, 2))[:, None].clamp_min(1))
        self.metal = MetalColour(mean.cpu().numpy(), allowed).to(self.texture.device)
        with torch.no_grad():
            scale = torch.where(torch.as_tensor(allowed, device=self.texture.device), float(rate), 1.0)
            self.metal_logit /= scale
            self.metal_scale.copy_(scale)

    def mix_metal(self, diffuse: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
        """The renderer's base colour: the diffuse, or with a metal colour (1 − m)·diffuse + m·c on the
        clusters allowed one."""
        if self.metal is None:
            return diffuse
        allowed = torch.einsum("k,khw->hw", self.metal.allowed, self.members)
        return self.metal.mix(diffuse, metallic * allowed, self.members)

    def metal_prior(self, lambda_l1: float, lambda_blend: float) -> torch.Tensor:
        """lambda_l1 × the area-weighted metallic of the clusters without a metal colour (sparsity) plus
        lambda_blend × metal_blend of those with one (metal or not, appearance.metal)."""
        if self.metal is None:
            return lambda_l1 * self.metallic_l1()
        m, allowed = self.cluster_values()["metallic"], self.metal.allowed
        return lambda_l1 * self.metallic_l1(1 - allowed) + lambda_blend * metal_blend(self.area * allowed, m)

    def forward(self, env: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The maps, the base colour with the clusters' metal colours where they have them (mix_metal)."""
        maps = self.base_maps(env)
        return {**maps, "diffuse": self.mix_metal(maps["diffuse"], maps["metallic"])}

    def base_maps(self, env: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The maps with the dielectric diffuse; env (the env map the renderer gets) is not used here
        (IrradianceMaps divides by it)."""
        s = self.size
        gain = Fnn.interpolate(self.gain, size=(s, s), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
        return {"diffuse": (self.detailed_texture() * torch.exp(gain)).clamp(0.0, 1.0), **self.material_maps()}

    @torch.no_grad()
    def set_matte(self, k: int) -> None:
        """Cluster k to roughness 1, metallic 0 (appearance.evidence: the data did not determine it)."""
        self.rough_logit[k] = 20.0
        self.metal_logit[k] = -20.0

    @torch.no_grad()
    def set_roughness(self, k: int, roughness: float) -> None:
        """Cluster k to this roughness, metallic 0 (appearance.evidence's band for an undetermined cluster)."""
        self.rough_logit[k] = 20.0 if roughness >= 1.0 else logit(roughness)
        self.metal_logit[k] = -20.0

    @torch.no_grad()
    def set_dielectric(self, k: int) -> None:
        """Cluster k to metallic 0 (a fitted metallic of a few per cent is noise, not a material)."""
        self.metal_logit[k] = -20.0

    def gain_chroma(self) -> torch.Tensor:
        """Mean over the gain grid's cells and channels of (G_c − mean_c G)²: 0 for any grey gain."""
        return (self.gain - self.gain.mean(dim=1, keepdim=True)).pow(2).mean()

    def metallic_l1(self, weight: torch.Tensor | None = None) -> torch.Tensor:
        """Area-weighted mean metallic (the sparsity prior), each cluster's share times `weight` (K,) if given."""
        area = self.area if weight is None else self.area * weight
        return (area * self.cluster_values()["metallic"]).sum()
