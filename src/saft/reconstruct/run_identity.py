"""What determines the result of a run: the scene's content and every config value that changes numbers.

A checkpoint stores this identity; `--resume` compares it with the run being started and refuses, naming
the keys that differ, when another scene or a config giving another result would continue it (otherwise
config.toml would misstate how the result was made).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from saft.config_io import to_dict
from saft.errors import SaftInputError

# Config keys that change when or how often state is saved, or how fast it runs, never the numbers.
NOT_RESULT_KEYS = frozenset({"run.checkpoint_seconds", "run.threads", "run.render_threads",
                             "appearance.checkpoint_every"})


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:12]


def _flatten(d: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def run_identity(scene, cfg, rgb: np.ndarray, mask: np.ndarray) -> dict[str, object]:
    """{key: value} of the result-determining config values and of the scene's parts (short digests).

    rgb, mask: the working frames the run fits (after crop and scale), so moved scene files still match.
    """
    ident = {k: (list(v) if isinstance(v, tuple) else v) for k, v in _flatten(to_dict(cfg)).items()
             if k not in NOT_RESULT_KEYS}
    t = scene.template
    cam = scene.camera
    ident.update({
        "scene.template": f"{t.num_vertices} vertices #{_digest(t.vertices, t.quads, t.uvs)}",
        "scene.camera": f"{cam.width}x{cam.height} #{_digest(cam.K, cam.world_to_camera)}",
        "scene.crop": None if scene.crop is None else str(scene.crop.to_json()),
        "scene.frames": f"{len(rgb)} frames #{_digest(rgb, mask)}",
        "scene.frame_dt": float(scene.frame_dt),
        "scene.gravity": [round(float(g), 12) for g in scene.gravity_or_default()],
        "scene.pinned": None if scene.pinned is None else f"{len(scene.pinned)} vertices #{_digest(scene.pinned)}",
        "scene.texture": None if scene.texture is None else f"#{_digest(scene.texture)}",
    })
    return ident


def check_same_run(saved: dict, current: dict, where: str | Path) -> None:
    """Raise SaftInputError naming the differing keys unless the checkpoint's identity equals the run's."""
    keys = sorted(set(saved) | set(current))
    differ = [k for k in keys if saved.get(k, "(absent)") != current.get(k, "(absent)")]
    if not differ:
        return
    shown = ", ".join(f"{k} ({saved.get(k, '(absent)')!s} -> {current.get(k, '(absent)')!s})" for k in differ[:6])
    more = f" and {len(differ) - 6} more" if len(differ) > 6 else ""
    raise SaftInputError(where, f"the checkpoint belongs to another run: {shown}{more} differ; resume with the "
                                "same scene and config, or pass --overwrite to start again")
