"""saft.export — what people look at and open elsewhere: the HTML report, videos, glTF, mesh sequences.

    report_command(result_dir, out=None) -> Path                        saft report DIR [--out FILE]
    export_command(result_dir, video=False, gltf=None, sequence=None,    saft export DIR [--video]
                   out_dir=None) -> list[Path]                            [--gltf OUT.glb] [--sequence obj|ply]
                                                                          [--out OUT_DIR]
Defaults: DIR/report.html; videos into OUT_DIR (default DIR/export/): comparison.mp4 (renders/),
appearance.mp4 (material/renders/, when present), orbit.mp4 (novel view); sequences into OUT_DIR/obj/ or
OUT_DIR/ply/. Modules: report, video, gltf, sequence (figures: the report's matplotlib plots).
"""

from saft.export.commands import export_command, report_command

__all__ = ["export_command", "report_command"]
