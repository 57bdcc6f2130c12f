"""The bodies of `saft report` and `saft export` (the CLI in saft.cli wires the flags to these)."""

from __future__ import annotations

import logging
from pathlib import Path

from saft.errors import SaftInputError
from saft.export.gltf import write_glb
from saft.export.report import write_report
from saft.export.sequence import write_sequence
from saft.export.video import comparison_video, orbit_video
from saft.result import list_render_files, read_result

log = logging.getLogger("saft")

DEFAULT_EXPORT_DIR = "export"


def report_command(result_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write the self-contained HTML report of a result folder (default DIR/report.html)."""
    return write_report(result_dir, out)


def export_command(result_dir: str | Path, video: bool = False, gltf: str | Path | None = None,
                   sequence: str | None = None, out_dir: str | Path | None = None) -> list[Path]:
    """Export a result: videos (--video), an animated .glb (--gltf FILE), a mesh sequence (--sequence obj|ply).

    Videos go to OUT_DIR (default DIR/export/), a sequence to OUT_DIR/obj/ or OUT_DIR/ply/; the .glb to the
    path given. Returns every file written. Raises SaftInputError when nothing is asked for or input is bad.
    """
    if not video and gltf is None and sequence is None:
        raise SaftInputError(None, "nothing to export: give --video, --gltf FILE.glb and/or --sequence obj|ply")
    if sequence is not None and sequence not in ("obj", "ply"):
        raise SaftInputError(None, f"--sequence must be obj or ply, got {sequence!r}")
    if gltf is not None and Path(gltf).suffix.lower() != ".glb":
        raise SaftInputError(gltf, "the glTF export is binary: give a file name ending in .glb")
    res = read_result(result_dir)
    out_dir = Path(out_dir) if out_dir is not None else res.folder / DEFAULT_EXPORT_DIR
    written: list[Path] = []
    if gltf is not None:
        written.append(write_glb(res, gltf))
    if sequence is not None:
        written += write_sequence(res, out_dir / sequence, sequence)
    if video:
        if list_render_files(res.folder):
            written.append(comparison_video(res, out_dir / "comparison.mp4")[0])
        else:
            log.warning("%s: no renders/frame_*.png, so no comparison video", res.folder)
        if list_render_files(res.folder, material=True):
            written.append(comparison_video(res, out_dir / "appearance.mp4", material=True)[0])
        written.append(orbit_video(res, out_dir / "orbit.mp4")[0])
    return written
