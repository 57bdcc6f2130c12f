"""`saft report DIR`: one self-contained report.html of a result folder (every image inlined, no network).

Sections: summary (titled with the scene's name), loss curves per phase (log.csv), the error against the
ground truth with readable names and units (metrics.json, when the run was evaluated), the fitted physical
parameters with their units and the fitted constant acceleration against the scene's gravity (params.json,
scene.json), texture and material maps, renders as labelled panels "rendered | target | |difference|" (the
difference as a colour map with its scale) with the appearance PSNR and an embedded, playable comparison
video at the scene's frame rate, the novel view as a strip through time, the depth difference
(depth/*.npz), the run's timings (timings.json) and config (config.toml). Each section that has no data
says so instead of failing.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import logging
import tempfile
from pathlib import Path

import numpy as np

from saft import __version__
from saft.appearance.fit import load_appearance
from saft.appearance.params import linear_to_srgb
from saft.evaluate import METRIC_LABELS
from saft.evaluate.appearance import read_appearance_ground_truth, resize_map
from saft.export import figures
from saft.export.video import comparison_frames, fps_of, write_mp4
from saft.io_utils import atomic_write_text, read_image
from saft.result import (
    Result,
    list_depth_files,
    list_render_files,
    read_config_dict,
    read_depth_pair,
    read_result,
)

log = logging.getLogger("saft")

MAX_INLINE_IMAGE_BYTES = 1_500_000   # larger maps are re-encoded at a smaller size
MAX_INLINE_IMAGE_SIDE = 1024
MAX_INLINE_VIDEO_BYTES = 12_000_000  # a longer comparison video is left to `saft export --video`
COMPARISON_ROWS = 4                  # frames shown as labelled panels per phase
NOVEL_STRIP_FRAMES = 6

# units of params.json entries (a result's own "units" take precedence)
PARAM_UNITS = {
    "Y": "N/m", "B": "N·m/rad²", "S": "N·m/rad²", "log10_Y": "log₁₀(Y / (N/m))", "log10_B": "log₁₀(B / (N·m/rad²))",
    "log10_S": "log₁₀(S / (N·m/rad²))", "constant_acceleration": "m/s²", "damping": "1 (velocity factor per substep)",
    "density": "kg/m²", "frame_dt": "s", "substeps": "per video frame",
}

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
video { max-width: 100%; border: 1px solid #ccc; background: #000; display: block; }
.speed button { margin: 4px 6px 0 0; }
p.note { color: #444; font-size: 0.9em; max-width: 900px; }
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
            ("frames", res.num_frames),
            ("frame rate", f"{1.0 / res.frame_dt:.4g} fps (frame_dt {res.frame_dt:g} s)" if res.frame_dt > 0 else "—"),
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
        rows = ""
        for name, mean in means.items():
            ys = series[name][1] if name in series else np.zeros(0)
            lo, hi = (f"{ys.min():.4g}", f"{ys.max():.4g}") if ys.size else ("—", "—")
            rows += (f"<tr><td>{html.escape(name)}</td><td class=\"num\">{mean:.4g}</td><td class=\"num\">{lo}</td>"
                     f"<td class=\"num\">{hi}</td></tr>")
        parts.append("<table><tr><th>metric (unit)</th><th>mean</th><th>best frame</th><th>worst frame</th></tr>"
                     f"{rows}</table>")
    if series:
        parts.append(_figure(figures.metrics_figure(series, means), "per-frame error; dashed: the mean"))
    return "".join(parts) or _none("metrics.json has no per-frame or mean values that can be plotted")


def _section_params(res: Result) -> str:
    if not res.params:
        return _none("no params.json")
    params = dict(res.params)
    own = params.pop("units", None)
    units = {**PARAM_UNITS, **(own if isinstance(own, dict) else {})}
    rows = [(k, v) for k, v in _flatten(params)]
    body = "".join(f"<tr><td>{html.escape(k)}</td><td class=\"num\">{html.escape(_fmt(v))}</td>"
                   f"<td>{html.escape(str(units.get(k, '—')))}</td></tr>" for k, v in rows)
    notes = "".join(f"<li>{html.escape(k)}: {html.escape(str(v))}</li>" for k, v in units.items()
                    if k not in params and k not in PARAM_UNITS)
    return (f"<table><tr><th>name</th><th>value</th><th>unit</th></tr>{body}</table>"
            + (f"<ul>{notes}</ul>" if notes else "") + _gravity_comparison(res))


def _scene_gravity(res: Result) -> tuple[np.ndarray | None, str]:
    """The scene's gravity (world frame, m/s²) and where it comes from."""
    g = res.scene_info.get("gravity")
    if g is not None:
        given = res.scene_info.get("gravity_given", True)
        return np.asarray(g, dtype=np.float64), ("given by the scene" if given else
                                                 "saft's default: 9.81 m/s² opposite the camera's image-up")
    if res.camera is not None:
        return -9.81 * res.camera.up / np.linalg.norm(res.camera.up), \
            "not recorded in scene.json; saft's default, 9.81 m/s² opposite the camera's image-up"
    return None, "not recorded in scene.json"


def _gravity_comparison(res: Result) -> str:
    a = res.params.get("constant_acceleration")
    if not (isinstance(a, list) and len(a) == 3):
        return ""
    a = np.asarray(a, dtype=np.float64)
    g, source = _scene_gravity(res)
    head = "<h3>Fitted constant acceleration against the scene's gravity</h3>"
    if g is None:
        return head + _none(f"gravity {source}: no comparison")
    na, ng = float(np.linalg.norm(a)), float(np.linalg.norm(g))
    angle = float(np.degrees(np.arccos(np.clip(a @ g / max(na * ng, 1e-12), -1.0, 1.0)))) if na > 0 and ng > 0 \
        else float("nan")
    rows = [("fitted constant acceleration a (m/s²)", [float(v) for v in a]),
            (f"scene gravity g (m/s²), {source}", [float(v) for v in g]),
            ("|a| (m/s²)", na), ("|g| (m/s²)", ng), ("|a| / |g|", na / ng if ng > 0 else float("nan")),
            ("angle between a and g (°)", angle), ("a − g (m/s²)", [float(v) for v in a - g])]
    return head + _table(rows, ("", "")) + (
        '<p class="note">The constant acceleration is fitted together with the per-vertex forces; where it '
        "differs from gravity the difference is carried by the cloth's supports (pinned vertices) or by the "
        "forces of the scene (wind, hands).</p>")


def _section_maps(res: Result) -> str:
    items = [(res.folder / "texture.png", "texture.png — phase-1 texture (sRGB)")]
    for name, caption in (("diffuse.png", "diffuse"), ("roughness.png", "roughness"), ("metallic.png", "metallic"),
                          ("normal.png", "normal"), ("envmap.png", "environment map")):
        p = res.material_path(name)
        if p is not None:
            items.append((p, f"material/{name} — {caption}"))
    parts = [_figure(_file_png(p), cap, "view" if p.name == "envmap.png" else "map")
             for p, cap in items if p.is_file()]
    try:   # what phase 3 says the video did not determine (appearance.evidence)
        note = json.loads((res.folder / "material" / "appearance.json").read_text()).get("undetermined")
    except (OSError, ValueError):
        note = None
    if note:
        parts.append(f'<p class="note">{html.escape(note)}</p>')
    return "".join(parts) or _none("no texture.png and no material maps")


def _srgb(x: np.ndarray) -> np.ndarray:
    import torch

    return linear_to_srgb(torch.as_tensor(np.ascontiguousarray(x, dtype=np.float32))).numpy()


def _better(gtm: dict, key: str, phase3_better: bool) -> str:
    if abs(gtm["phase3"][key] - gtm["texture_only"][key]) < 1e-9:
        return "tie"
    return "phase 3" if phase3_better else "texture only"


def _section_appearance_gt(res: Result) -> str | None:
    """Phase 3 against the scene's appearance ground truth (saft evaluate wrote it into appearance.json):
    the metrics beside the texture-only baseline and each map | its truth | |error|; None without them."""
    try:
        gtm = json.loads((res.folder / "material" / "appearance.json").read_text()).get("ground_truth_metrics")
    except (OSError, ValueError):
        gtm = None
    if not gtm:
        return None
    parts = []
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td class=\"num\">{gtm['phase3'][k]:.3f}</td>"
                   f"<td class=\"num\">{gtm['texture_only'][k]:.3f}</td>"
                   f"<td>{_better(gtm, k, better)}</td></tr>" for k, better in gtm["phase3_better"].items())
    parts.append("<table><tr><th>metric</th><th>phase 3</th><th>texture only</th><th>better</th></tr>"
                 f"{rows}</table>")
    gt = read_appearance_ground_truth(gtm["scene"]) if Path(gtm["scene"]).is_dir() else None
    if gt is None:
        return "".join(parts) + _none(f"the ground-truth scene {gtm['scene']} is not here: no map comparison")
    est = load_appearance(res.folder)
    scale = np.asarray(gtm["phase3"]["diffuse_scale"], np.float32)
    size = gt.roughness.shape[:2]
    for name, mine, truth in (("diffuse (× per-channel scale, sRGB)", est.diffuse * scale, gt.base_color),
                              ("roughness", est.roughness, gt.roughness), ("metallic", est.metallic, gt.metallic)):
        a, b = np.atleast_3d(resize_map(mine, size)), np.atleast_3d(truth)
        if name.startswith("diffuse"):
            a, b = _srgb(np.clip(a, 0, 1)), _srgb(b)
        err = np.abs(a - b).mean(axis=2, keepdims=True)
        panel = np.concatenate([np.broadcast_to(x, (*size, 3)) for x in (a, b, err)], axis=1)
        parts.append(_figure(figures.array_to_png(np.clip(panel, 0, 1)), f"{name}: estimate | truth | |error|",
                             ""))
    return "".join(parts)


def _spread(items: list, n: int) -> list:
    """n items evenly spread over the list (first and last included)."""
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))]


def _panel_pairs(files: list[Path], n_panels: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    out = []
    for p in files:
        panels = figures.split_panels(read_image(p), n_panels)
        out.append((int(p.stem.split("_")[-1]) if p.stem.split("_")[-1].isdigit() else len(out), panels[0], panels[1]))
    return out


def _psnrs(pairs: list[tuple[int, np.ndarray, np.ndarray]]) -> np.ndarray:
    """Per frame: PSNR over the pixels where the rendering or the target shows cloth (is not black)."""
    vals = []
    for _, rendered, target in pairs:
        mask = (rendered[:, :, :3].max(axis=2) > 0.02) | (target[:, :, :3].max(axis=2) > 0.02)
        vals.append(figures.psnr(rendered, target, mask))
    return np.asarray(vals)


def _fit_note(res: Result, n_frames: int, appearance: bool) -> str:
    app = read_config_dict(res.folder).get("appearance", {})
    per_epoch = int(app.get("frames_per_epoch", 0) or 0)
    batches = f" in random mini-batches of {per_epoch} frames" if 0 < per_epoch < n_frames else ""
    phase3 = f" and phase 3 fitted the material on all {n_frames} frames{batches}" if appearance else ""
    return (f"Held-out frames: none. Phase 2 fits the shape to every frame{phase3}; these PSNRs therefore "
            "measure how well the fit reproduces the frames it was fitted to, not how it generalises to unseen "
            "frames. PSNR is over the pixels where the rendering or the target shows cloth (not black).")


def _video(res: Result, material: bool) -> str:
    """The labelled comparison video as an embedded, playable <video> (with speed buttons)."""
    fps = fps_of(res)
    with tempfile.TemporaryDirectory() as tmp:
        frames = comparison_frames(list_render_files(res.folder, material), res.frame_dt, material)
        path, n = write_mp4(Path(tmp) / "comparison.mp4", frames, fps)
        data = path.read_bytes()
    what = "appearance re-render" if material else "shape-phase rendering"
    if len(data) > MAX_INLINE_VIDEO_BYTES:
        return _none(f"the {what} video ({len(data) / 1e6:.1f} MB) is too large to embed; "
                     "saft export --video writes it")
    vid = "video-appearance" if material else "video-shape"
    buttons = "".join(f'<button type="button" onclick="document.getElementById(\'{vid}\').playbackRate={r}">'
                      f"{label}</button>" for r, label in ((1, "1× (real time)"), (0.5, "½×"), (0.25, "¼×")))
    return (f'<figure><video id="{vid}" controls loop muted autoplay playsinline '
            f'src="data:video/mp4;base64,{base64.b64encode(data).decode("ascii")}"></video>'
            f'<div class="speed">{buttons}</div><figcaption>{html.escape(what)} | target | |difference|: {n} frames '
            f"at the scene's {fps:.4g} fps ({n / fps:.2f} s)</figcaption></figure>")


def _section_renders(res: Result, max_frames: int) -> str:
    parts = []
    psnr_rows = []
    for material, label, first, n_panels in ((False, "phase 2 (shape): textured rendering", "rendered", 3),
                                              (True, "phase 3 (appearance): re-render", "re-render", 2)):
        files = list_render_files(res.folder, material=material)
        if not files:
            continue
        pairs = _panel_pairs(files, n_panels)
        shown = _spread(pairs, min(max_frames, COMPARISON_ROWS))
        parts.append(f"<h3>{html.escape(label)}</h3>")
        parts.append(_figure(figures.comparison_figure([(f"frame {k}", r, t) for k, r, t in shown], first),
                             f"{first} | target | |difference|: {len(shown)} of {len(files)} frames"))
        parts.append(_video(res, material))
        ps = _psnrs(pairs)
        ok = ps[np.isfinite(ps)]
        psnr_rows.append((label, len(files), ok))
    if not parts:
        return _none("no renders/frame_*.png")
    body = "".join(f"<tr><td>{html.escape(label)}</td><td class=\"num\">{n}</td>"
                   f"<td class=\"num\">{ok.mean():.2f}</td><td class=\"num\">{ok.min():.2f}</td>"
                   f"<td class=\"num\">{ok.max():.2f}</td><td>all (none held out)</td></tr>"
                   for label, n, ok in psnr_rows if ok.size)
    table = ("<h3>PSNR</h3><table><tr><th>images</th><th>frames</th><th>mean PSNR (dB)</th><th>min (dB)</th>"
             f"<th>max (dB)</th><th>frames used for fitting</th></tr>{body}</table>"
             f'<p class="note">{html.escape(_fit_note(res, res.num_frames, len(psnr_rows) > 1))}</p>')
    return table + "".join(parts)


def _section_novel(res: Result) -> str:
    folder = res.folder / "material" / "novel_view"
    files = sorted(folder.glob("frame_*.png")) if folder.is_dir() else []
    if not files:
        return _none("no material/novel_view/ (phase 3 renders the cloth from a camera turned 45° about it)")
    shown = _spread(files, NOVEL_STRIP_FRAMES)
    frames = []
    for p in shown:
        k = int(p.stem.split("_")[-1]) if p.stem.split("_")[-1].isdigit() else 0
        frames.append((f"frame {k}, t = {k * res.frame_dt:.2f} s", read_image(p)))
    return _figure(figures.strip_figure(frames, "novel view: the camera turned 45° around the cloth, "
                                                "with the fitted material and light"),
                   f"{len(shown)} of {len(files)} frames of material/novel_view/")


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
        ("renders", "Renders: rendered | target | |difference|", _section_renders(res, max_frames)),
        ("novel", "Novel view", _section_novel(res)),
        ("depth", "Depth difference", _section_depth(res)),
        ("timings", "Timings", _section_timings(res)),
        ("config", "Config", _section_config(res)),
    ]
    appearance = _section_appearance_gt(res)
    if appearance is not None:   # only where saft evaluate scored phase 3 against known maps
        sections.insert(5, ("appearance", "Appearance against ground truth", appearance))
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

