"""`saft report DIR`: one self-contained report.html of a result folder (every image inlined, no network).

Sections: summary, loss curves per phase (log.csv), per-frame CD2/CD1/p2s (metrics.json, when the run
was evaluated), fitted physical parameters (params.json), texture and material maps, contact sheets of
renders/ (rendered | target | difference) and material/renders/, the depth difference (depth/*.npz, when
depth ground truth exists), the run's timings (timings.json) and config (config.toml). Each section that
has no data says so instead of failing.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import logging
from pathlib import Path

import numpy as np

from saft import __version__
from saft.export import figures
from saft.io_utils import atomic_write_text
from saft.result import Result, list_depth_files, list_render_files, read_depth_pair, read_result

log = logging.getLogger("saft")

MAX_INLINE_IMAGE_BYTES = 1_500_000   # larger maps are re-encoded at a smaller size
MAX_INLINE_IMAGE_SIDE = 1024

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0; color: #222; background: #fafafa; }
header { background: #24344d; color: #fff; padding: 18px 28px; }
header h1 { margin: 0 0 4px 0; font-size: 1.5em; }
header p { margin: 0; opacity: 0.85; }
nav { padding: 8px 28px; background: #e8ecf2; font-size: 0.9em; }
nav a { margin-right: 14px; color: #24344d; }
main { padding: 8px 28px 40px 28px; max-width: 1100px; }
section { margin-top: 26px; }
h2 { border-bottom: 2px solid #24344d; padding-bottom: 4px; font-size: 1.2em; }
figure { display: inline-block; margin: 6px 14px 14px 0; vertical-align: top; }
figure img { max-width: 100%; border: 1px solid #ccc; background: #fff; image-rendering: auto; }
figure.map img { width: 256px; height: auto; image-rendering: pixelated; }
figure.view img { width: 384px; height: auto; }
figcaption { font-size: 0.85em; color: #555; margin-top: 3px; }
table { border-collapse: collapse; font-size: 0.92em; }
td, th { border: 1px solid #ccc; padding: 3px 10px; text-align: left; }
th { background: #eef1f5; }
td.num { text-align: right; font-family: ui-monospace, monospace; }
pre { background: #fff; border: 1px solid #ccc; padding: 10px; overflow-x: auto; font-size: 0.85em; }
p.none { color: #777; font-style: italic; }
"""


def _img_tag(png: bytes, alt: str, mime: str = "image/png") -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:{mime};base64,{data}" alt="{html.escape(alt)}">'


def _figure(png: bytes, caption: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f"<figure{c}>{_img_tag(png, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>"


def _file_png(path: Path) -> bytes:
    """The PNG bytes of an image file, re-encoded (downsized) only when it is large or not a PNG."""
    raw = path.read_bytes()
    if path.suffix.lower() == ".png" and len(raw) <= MAX_INLINE_IMAGE_BYTES:
        return raw
    from PIL import Image

    with Image.open(io.BytesIO(raw)) as im:
        im = im.convert("RGBA" if im.mode in ("RGBA", "LA", "P") else "RGB")
        im.thumbnail((MAX_INLINE_IMAGE_SIDE, MAX_INLINE_IMAGE_SIDE))
        buf = io.BytesIO()
        im.save(buf, format="PNG")
        return buf.getvalue()


def _none(text: str) -> str:
    return f'<p class="none">{html.escape(text)}</p>'


def _fmt(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.6g}"
    if isinstance(value, (list, tuple)):
        arr = np.asarray(value, dtype=object)
        if arr.size > 12:
            try:
                num = np.asarray(value, dtype=np.float64)
                return f"array {tuple(num.shape)}, min {num.min():.4g}, mean {num.mean():.4g}, max {num.max():.4g}"
            except (TypeError, ValueError):
                return f"list of {len(value)}"
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flatten(v, key + ".")
        else:
            out.append((key, v))
    return out


def _table(rows: list[tuple[str, object]], head: tuple[str, str] = ("name", "value")) -> str:
    body = "".join(f"<tr><td>{html.escape(str(k))}</td><td class=\"num\">{html.escape(_fmt(v))}</td></tr>"
                   for k, v in rows)
    top = f"<tr><th>{html.escape(head[0])}</th><th>{html.escape(head[1])}</th></tr>" if any(head) else ""
    return f"<table>{top}{body}</table>"


# ---------------------------------------------------------------------------- sections
def _section_summary(res: Result) -> str:
    info = res.scene_info
    rows = [("scene", info.get("name", res.folder.name)), ("source", info.get("source", "—")),
            ("frames", res.num_frames), ("frame_dt (s)", res.frame_dt),
            ("template", f"{res.template.num_vertices} vertices, {len(res.template.quads)} quads")]
    if res.camera is not None:
        c = res.camera
        rows.append(("working camera", f"{c.width}×{c.height} px, fx={c.fx:.2f} fy={c.fy:.2f}"))
    extent = res.vertices.reshape(-1, 3)
    size = extent.max(axis=0) - extent.min(axis=0)
    rows.append(("bounding box over all frames (m)", [float(s) for s in size]))
    return _table(rows, ("", ""))


def _section_losses(res: Result) -> str:
    series = figures.loss_series(res.log_rows)
    if not series:
        return _none("no log.csv (or no numeric loss columns in it)")
    parts = []
    for phase, terms in series.items():
        parts.append(_figure(figures.loss_figure(phase, terms), f"loss terms of phase '{phase}' per epoch"))
    return "".join(parts)


def _section_metrics(res: Result) -> str:
    if not res.metrics:
        return _none("no metrics.json: the run was not evaluated against ground truth (saft evaluate)")
    series, means = figures.metrics_series(res.metrics)
    parts = []
    if means:
        parts.append(_table(sorted(means.items()), ("metric", "mean")))
    if series:
        parts.append(_figure(figures.metrics_figure(series, means), "per-frame " + ", ".join(sorted(series))))
    return "".join(parts) or _none("metrics.json has no per-frame or mean values that can be plotted")


def _section_params(res: Result) -> str:
    if not res.params:
        return _none("no params.json")
    params = dict(res.params)
    units = params.pop("units", None)
    units = units if isinstance(units, dict) else {}
    rows = [(k, v) for k, v in _flatten(params)]
    body = "".join(f"<tr><td>{html.escape(k)}</td><td class=\"num\">{html.escape(_fmt(v))}</td>"
                   f"<td>{html.escape(str(units.get(k, '')))}</td></tr>" for k, v in rows)
    notes = "".join(f"<li>{html.escape(k)}: {html.escape(str(v))}</li>" for k, v in units.items()
                    if k not in params)
    return (f"<table><tr><th>name</th><th>value</th><th>unit</th></tr>{body}</table>"
            + (f"<ul>{notes}</ul>" if notes else ""))


def _section_maps(res: Result) -> str:
    items = [(res.folder / "texture.png", "texture.png — phase-1 texture (sRGB)")]
    for name, caption in (("diffuse.png", "diffuse"), ("roughness.png", "roughness"), ("metallic.png", "metallic"),
                          ("normal.png", "normal"), ("envmap.png", "environment map"),
                          ("novel_view.png", "novel view")):
        p = res.material_path(name)
        if p is not None:
            items.append((p, f"material/{name} — {caption}"))
    parts = [_figure(_file_png(p), cap, "view" if p.name in ("envmap.png", "novel_view.png") else "map")
             for p, cap in items if p.is_file()]
    return "".join(parts) or _none("no texture.png and no material maps")


def _section_renders(res: Result, max_frames: int) -> str:
    parts = []
    files = list_render_files(res.folder)
    if files:
        parts.append(_figure(figures.contact_sheet(files, max_frames, "rendered | target | |difference|"),
                             f"renders/: {min(len(files), max_frames)} of {len(files)} frames"))
    mat = list_render_files(res.folder, material=True)
    if mat:
        parts.append(_figure(figures.contact_sheet(mat, max_frames, "appearance phase"),
                             f"material/renders/: {min(len(mat), max_frames)} of {len(mat)} frames"))
    novel = res.folder / "material" / "novel_view"
    novel_files = sorted(novel.glob("frame_*.png")) if novel.is_dir() else []
    if novel_files:
        parts.append(_figure(figures.contact_sheet(novel_files, max_frames, "novel view"),
                             f"material/novel_view/: {min(len(novel_files), max_frames)} of {len(novel_files)} frames"))
    return "".join(parts) or _none("no renders/frame_*.png")


def _section_depth(res: Result, max_frames: int = 4) -> str:
    files = list_depth_files(res.folder)
    if not files:
        return _none("no depth ground truth for this scene (depth/frame_*.npz)")
    if len(files) > max_frames:
        idx = np.unique(np.round(np.linspace(0, len(files) - 1, max_frames)).astype(int))
        files = [files[i] for i in idx]
    pairs = [(p.stem, *read_depth_pair(p)) for p in files]
    return _figure(figures.depth_figure(pairs), "depth: rendered, target and rendered − target")


def _section_timings(res: Result) -> str:
    nums = {k: float(v) for k, v in res.timings.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    if not nums:
        return _none("no timings.json")
    return _table([(k, f"{v:.2f} s") for k, v in nums.items()], ("phase", "time")) + \
        _figure(figures.timings_figure(nums), "seconds per phase")


def _section_config(res: Result) -> str:
    if res.config_text is None:
        return _none("no config.toml")
    return f"<pre>{html.escape(res.config_text)}</pre>"


def build_report_html(res: Result, max_frames: int = 8) -> str:
    sections = [
        ("summary", "Summary", _section_summary(res)),
        ("losses", "Loss curves", _section_losses(res)),
        ("metrics", "Error against ground truth", _section_metrics(res)),
        ("params", "Fitted physical parameters", _section_params(res)),
        ("maps", "Texture and material maps", _section_maps(res)),
        ("renders", "Renders (rendered | target | difference)", _section_renders(res, max_frames)),
        ("depth", "Depth difference", _section_depth(res)),
        ("timings", "Timings", _section_timings(res)),
        ("config", "Config", _section_config(res)),
    ]
    name = res.scene_info.get("name", res.folder.name)
    nav = "".join(f'<a href="#{sid}">{html.escape(title)}</a>' for sid, title, _ in sections)
    body = "".join(f'<section id="{sid}"><h2>{html.escape(title)}</h2>{content}</section>'
                   for sid, title, content in sections)
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            "<link rel=\"icon\" href=\"data:,\">"
            f"<title>saft report — {html.escape(str(name))}</title><style>{_CSS}</style></head><body>"
            f"<header><h1>saft reconstruction: {html.escape(str(name))}</h1>"
            f"<p>{html.escape(str(res.folder.resolve()))} · {res.num_frames} frames · saft {__version__} · {stamp}</p>"
            f"</header><nav>{nav}</nav><main>{body}</main></body></html>\n")


def write_report(result_dir: str | Path, out: str | Path | None = None, max_frames: int = 8) -> Path:
    """Write the self-contained HTML report of a result folder (default DIR/report.html); returns its path."""
    res = read_result(result_dir)
    out = Path(out) if out is not None else res.folder / "report.html"
    atomic_write_text(out, build_report_html(res, max_frames=max_frames))
    log.info("wrote %s", out)
    return out

