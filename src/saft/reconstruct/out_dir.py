"""The output folder of `reconstruct`: checked before anything is written, so that no scene, no foreign
folder and no earlier result is ever damaged by accident.

Rules (README "Result folder"):
- OUT must not be a file, lie under a file, or be on a file system saft cannot write to;
- OUT must not be the scene's folder nor contain the scene (its folder, JSON, frames or masks);
- an existing OUT must be empty or hold a saft result; a saft result is only written into again with
  `--resume` (continue its checkpoint) or `--overwrite` (its files are removed first, so no stale
  frame_NNN.obj of the old run survives).
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from pathlib import Path

from saft.errors import SaftInputError
from saft.reconstruct.checkpoint import checkpoint_path

# Everything a run, `saft evaluate`, `saft report` and `saft export` write into a result folder (saft.result).
RESULT_ENTRIES = ("config.toml", "scene.json", "meshes", "texture.png", "params.json", "forces.npy", "renders",
                  "log.csv", "timings.json", "metrics.json", "depth", "material", "checkpoint", "report.html",
                  "export")


def is_saft_result(folder: Path) -> bool:
    """A folder a saft run wrote: its config.toml and a checkpoint or meshes/."""
    folder = Path(folder)
    return (folder / "config.toml").is_file() and (checkpoint_path(folder).is_file() or (folder / "meshes").is_dir())


def _scene_paths(scene) -> list[Path]:
    paths = [Path(scene.source)] if scene.source is not None else []
    frames = scene.frames
    paths.append(Path(frames.rgb_paths[0]).parent)
    if frames.mask_paths:
        paths.append(Path(frames.mask_paths[0]).parent)
    return paths


def _nearest_existing(path: Path) -> Path:
    return next(p for p in (path, *path.parents) if p.exists() or p.is_symlink())


def check_out_dir(out_dir: str | Path, scene, *, resume: bool, overwrite: bool) -> None:
    """Refuse an unusable or unsafe output folder (SaftInputError naming it); writes nothing."""
    out = Path(out_dir)
    existing = _nearest_existing(out.absolute())
    if not existing.is_dir():
        raise SaftInputError(out, "is a file, not a folder" if existing == out.absolute() else
                             f"cannot be created: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise SaftInputError(out, f"cannot be written: no write permission in {existing} (or a read-only file system)")
    resolved = out.resolve()
    for p in _scene_paths(scene):
        p = p.resolve()
        if p == resolved or resolved in p.parents:
            raise SaftInputError(out, f"is or contains the scene ({p}); write the result to a folder outside it")
    if not out.is_dir() or not any(out.iterdir()):
        return
    if not is_saft_result(out):
        raise SaftInputError(out, "is not empty and holds no saft result; give a new or empty folder")
    if resume:
        if not checkpoint_path(out).is_file():
            raise SaftInputError(out, "holds a saft result without a checkpoint, so there is nothing to resume; "
                                      "pass --overwrite to start again")
        return
    if not overwrite:
        raise SaftInputError(out, "already holds a saft result; pass --overwrite to replace it or --resume to "
                                  "continue an interrupted run")


def create_out_dir(out_dir: str | Path, *, overwrite: bool) -> None:
    """Create the folder (removing an old result's files with overwrite=True) and prove it writable."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        if overwrite:
            for name in RESULT_ENTRIES:
                p = out / name
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                elif p.exists() or p.is_symlink():
                    p.unlink()
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if exc.errno == errno.EROFS:
            reason = "read-only file system"
        raise SaftInputError(out, f"cannot be written ({reason})") from None
