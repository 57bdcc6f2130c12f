"""Range checks of a SaftConfig: a value of the right type but outside what the method can use is rejected
with one line naming the key (e.g. `--set render.scale=0`, a negative epoch count).

The types are checked when the config is read (saft.config_io); these are the numeric bounds on top.
"""

from __future__ import annotations

import math

from saft.errors import SaftInputError

INF = math.inf

# key: (lowest, highest, lowest allowed itself). Keys missing from the config (renamed by another
# version) are skipped; bounds are what the code can run with, not what gives good results.
RANGES: dict[str, tuple[float, float, bool]] = {
    "run.seed": (0, INF, True),
    "run.threads": (0, 1024, True),
    "run.render_threads": (0, 64, True),
    "run.checkpoint_seconds": (0, INF, True),
    "render.scale": (0, 4, False),
    "texture.epochs": (0, 1_000_000, True),
    "texture.size": (4, 8192, True),
    "texture.init_value": (0, 1, True),
    "texture.lr": (0, INF, True),
    "texture.lambda_smooth": (0, INF, True),
    "physics.substeps": (1, 1000, True),
    "physics.density": (0, INF, False),
    "physics.damping": (0, 1, False),
    "physics.swing_damping": (0, 1, True),
    "physics.swing_run_damping": (0, 1, True),
    "physics.air_drag": (0, INF, True),
    "shape.initial_frames": (1, INF, True),
    "shape.add_frame_every": (1, INF, True),
    "shape.final_epochs": (0, 1_000_000, True),
    "shape.plateau_max_extra": (0, 1_000_000, True),
    "shape.plateau_tol": (0, 1, True),
    "shape.lambda_image": (0, INF, True),
    "shape.lambda_sil": (0, INF, True),
    "shape.swing_lambda_sil": (0, INF, True),
    "shape.sil_reach_px": (0, 255, True),
    "shape.sil_reach_gain": (0, INF, True),
    "shape.lambda_energy": (0, INF, True),
    "shape.lambda_force": (0, INF, True),
    "shape.force_along_weight": (0, 1, True),
    "shape.force_along_weight_pinned": (0, 1, True),
    "shape.lr_stiffness": (0, INF, True),
    "shape.lr_air_drag": (0, INF, True),
    "shape.lr_const_accel": (0, INF, True),
    "shape.lr_vertex_accel": (0, INF, True),
    "shape.lr_field_accel": (0, INF, True),
    "shape.lr_light": (0, INF, True),
    "shape.plain_shading": (0, INF, True),
    "shape.lr_v0": (0, INF, True),
    "shape.lambda_v0": (0, INF, True),
    "shape.lr_anchor": (0, INF, True),
    "shape.lambda_anchor": (0, INF, True),
    "shape.grad_clip": (0, INF, False),
    "shape.autoclip_quantile": (0, 1, False),
    "shape.autoclip_history": (1, INF, True),
    "shape.initial_epochs": (0, 1_000_000, True),
    "shape.lambda_track": (0, INF, True),
    "shape.track_fb_threshold": (0, INF, False),
    "shape.track_huber": (0, INF, False),
    "shape.track_reanchor_radius": (0, INF, True),
    "shape.track_jump_ratio": (0, INF, True),
    "shape.track_jump_floor": (0, 1, True),
    "shape.track_drift": (0, 1, True),
    "shape.track_drift_scale": (0, 1, True),
    "shape.track_texture": (0, INF, True),
    "shape.final_lr_fraction": (0, 1, False),
    "shape.backtrack_ratio": (0, INF, True),
    "shape.backtrack_decay": (0, 1, False),
    "shape.backtrack_recover_epochs": (0, 1_000_000, True),
    "shape.window": (0, INF, True),
    "shape.full_pass_every": (0, INF, True),
    "appearance.epochs": (1, 1_000_000, True),
    "appearance.checkpoint_every": (0, INF, True),
    "appearance.render_spp": (1, 1_000_000, True),
    "appearance.texel_size": (4, 8192, True),
    "appearance.gain_grid": (1, 4096, True),
    "appearance.clusters": (1, 64, True),
    "appearance.texture_smoothing": (0, INF, True),
    "appearance.lambda_metallic_l1": (0, INF, True),
    "appearance.lambda_gain_chroma": (0, INF, True),
    "appearance.evidence_threshold": (0, INF, True),
    "appearance.evidence_spp": (1, 1_000_000, True),
}

# Ranges [lo, hi] given in the config, each with the initial value that must lie in it: the log10
# stiffnesses and the soft anchors' log10 stiffness.
INIT_IN_RANGE = tuple((f"physics.log10_{n}_init", f"physics.log10_{n}_range") for n in ("Y", "B", "S")) + (
    ("shape.anchor_log10_init", "shape.anchor_log10_range"),)


def _get(cfg, key: str):
    node = cfg
    for part in key.split("."):
        if not hasattr(node, part):
            return None
        node = getattr(node, part)
    return node


def check_config_ranges(cfg, where: str = "config") -> None:
    """Raise SaftInputError naming the first key whose value is out of its range."""
    for key, (lo, hi, lo_inclusive) in RANGES.items():
        value = _get(cfg, key)
        if value is None:
            continue
        low_ok = value >= lo if lo_inclusive else value > lo
        if not low_ok or value > hi:   # NaN fails low_ok
            bracket = "[" if lo_inclusive else "("
            raise SaftInputError(where, f"{key} must lie in {bracket}{lo:g}, {hi:g}], got {value!r}")
    drag, (lo, hi) = _get(cfg, "physics.air_drag"), _get(cfg, "physics.air_drag_range") or (None, None)
    if lo is not None and not (0 < lo <= hi < INF):
        raise SaftInputError(where, f"physics.air_drag_range must be [low, high] with 0 < low <= high, got [{lo!r}, {hi!r}]")
    if drag and lo is not None and not lo <= drag <= hi:
        raise SaftInputError(where, f"physics.air_drag = {drag!r} lies outside physics.air_drag_range [{lo:g}, {hi:g}]")
    for init_key, range_key in INIT_IN_RANGE:
        lo, hi = _get(cfg, range_key) or (None, None)
        init = _get(cfg, init_key)
        if lo is None or init is None:
            continue
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise SaftInputError(where, f"{range_key} must be [low, high] with low <= high, got [{lo!r}, {hi!r}]")
        if not lo <= init <= hi:
            raise SaftInputError(where, f"{init_key} = {init!r} lies outside {range_key} [{lo:g}, {hi:g}]")
