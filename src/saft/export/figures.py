"""Matplotlib figures of a result, returned as PNG bytes (headless Agg backend, no display needed)."""

from __future__ import annotations

import io
import math

import numpy as np

from saft.evaluate import METRIC_LABELS

# columns of log.csv that are not loss terms
LOG_META_COLUMNS = {"phase", "epoch", "frames", "frames_in_use", "seconds", "time", "lr", "step"}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def fig_to_png(fig, dpi: int = 100) -> bytes:
    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def array_to_png(img: np.ndarray) -> bytes:
    """A float [0, 1] or uint8 image (H×W, H×W×1/3/4) as PNG bytes."""
    from PIL import Image

    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = (np.clip(np.nan_to_num(a.astype(np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _float(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def loss_series(log_rows: list[dict]) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """{phase: {loss term: (x, y)}} from log.csv rows; x is the epoch (or the row number without one)."""
    out: dict[str, dict[str, tuple[list, list]]] = {}
    for n, row in enumerate(log_rows):
        phase = str(row.get("phase") or "run")
        x = _float(row.get("epoch"))
        x = float(n) if x is None else x
        for key, val in row.items():
            if key is None or key.strip().lower() in LOG_META_COLUMNS:
                continue
            y = _float(val)
            if y is None:
                continue
            xs, ys = out.setdefault(phase, {}).setdefault(key, ([], []))
            xs.append(x)
            ys.append(y)
    return {ph: {k: (np.asarray(xs), np.asarray(ys)) for k, (xs, ys) in terms.items()} for ph, terms in out.items()}


def loss_figure(phase: str, terms: dict[str, tuple[np.ndarray, np.ndarray]]) -> bytes:
    """Every loss term of a phase against the epoch, on a log scale (terms differ by orders of magnitude);
    zero or negative values are left out of the log plot, terms that are never positive are listed."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 3.6), layout="constrained")
    skipped = []
    for name, (x, y) in sorted(terms.items()):
        ok = y > 0
        if not ok.any():
            skipped.append(name)
            continue
        ax.plot(x[ok], y[ok], label=name, lw=1.5, marker="." if ok.sum() < 30 else None)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (log scale)")
    ax.set_title(f"phase: {phase}" + (f"  (always 0: {', '.join(skipped)})" if skipped else ""), fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    if len(skipped) < len(terms):
        ax.legend(fontsize=8)
    return fig_to_png(fig)


def metrics_series(metrics: dict) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """Per-frame series {name: (frames, values)} and means {name: value} from metrics.json.

    Accepts per-frame values as a list of {"frame": i, name: value, ...} records or as {name: [values]},
    under "per_frame" (or "frames"); means under "mean" (or "means").
    """
    per = metrics.get("per_frame", metrics.get("frames"))
    units = metrics.get("units") if isinstance(metrics.get("units"), dict) else {}
    series: dict[str, tuple[list, list]] = {}
    if isinstance(per, list):
        for n, rec in enumerate(per):
            if not isinstance(rec, dict):
                continue
            f = _float(rec.get("frame"))
            f = float(n) if f is None else f
            for k, v in rec.items():
                y = _float(v) if not isinstance(v, bool) else None
                if k == "frame" or y is None:
                    continue
                xs, ys = series.setdefault(k, ([], []))
                xs.append(f)
                ys.append(y)
    elif isinstance(per, dict):
        frames = per.get("frame")
        for k, vals in per.items():
            if k == "frame" or not isinstance(vals, list):
                continue
            pts = [(float(frames[i]) if isinstance(frames, list) and i < len(frames) else float(i), _float(v))
                   for i, v in enumerate(vals)]
            pts = [(x, y) for x, y in pts if y is not None]
            if pts:
                series[k] = ([x for x, _ in pts], [y for _, y in pts])
    mean_src = metrics.get("mean", metrics.get("means", {}))
    means = {}
    if isinstance(mean_src, dict):
        means = {k: v for k, v in ((k, _float(v)) for k, v in mean_src.items()) if v is not None}

    def label(k: str) -> str:
        """The readable name with its unit ("CD2 (10⁻⁴ m²)"), else the key with metrics.json's unit."""
        return METRIC_LABELS.get(k) or (f"{k} ({units[k]})" if k in units else k)

    keep = [k for k in series if not k.startswith("num_")]  # counts (e.g. num_gt_points) are not errors
    return ({label(k): (np.asarray(series[k][0]), np.asarray(series[k][1])) for k in keep},
            {label(k): v for k, v in means.items() if not k.startswith("num_")})


def metrics_figure(series: dict[str, tuple[np.ndarray, np.ndarray]], means: dict[str, float]) -> bytes:
    plt = _plt()
    names = sorted(series)
    fig, axes = plt.subplots(len(names), 1, figsize=(6.4, 0.6 + 1.9 * len(names)), squeeze=False, sharex=True,
                             layout="constrained")
    for ax, name in zip(axes[:, 0], names):
        x, y = series[name]
        ax.plot(x, y, marker="o", ms=3, lw=1.2)
        if name in means:
            ax.axhline(means[name], color="gray", ls="--", lw=1, label=f"mean {means[name]:.4g}")
            ax.legend(fontsize=8)
        ax.set_ylabel(name.replace(" (", "\n("), fontsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("frame")
    fig.suptitle("per-frame error against the ground truth")
    return fig_to_png(fig)


def timings_figure(timings: dict[str, float]) -> bytes:
    plt = _plt()
    names = list(timings)
    fig, ax = plt.subplots(figsize=(6.4, 0.8 + 0.4 * len(names)), layout="constrained")
    ax.barh(names, [timings[n] for n in names], color="#4a7ab5")
    ax.invert_yaxis()
    ax.set_xlabel("seconds")
    ax.grid(True, axis="x", alpha=0.3)
    return fig_to_png(fig)


def depth_figure(pairs: list[tuple[str, np.ndarray, np.ndarray]]) -> bytes:
    """Per frame: rendered depth, target depth (one shared colour scale) and their signed difference in mm."""
    plt = _plt()
    fig, axes = plt.subplots(len(pairs), 3, figsize=(10.5, 3.0 * len(pairs)), squeeze=False)
    for row, (label, rendered, target) in zip(axes, pairs):
        rendered = np.where(rendered > 0, rendered, np.nan)  # 0 = no surface, like NaN
        target = np.where(target > 0, target, np.nan)
        both = np.concatenate([rendered[np.isfinite(rendered)], target[np.isfinite(target)]])
        lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
        diff_mm = (rendered - target) * 1000.0
        lim = float(np.nanmax(np.abs(diff_mm))) if np.isfinite(diff_mm).any() else 1.0
        ok = np.isfinite(diff_mm)
        mean_abs = float(np.abs(diff_mm[ok]).mean()) if ok.any() else float("nan")
        for ax, img, ttl, kw in (
            (row[0], rendered, f"{label}: rendered depth (m)", dict(cmap="viridis", vmin=lo, vmax=hi)),
            (row[1], target, f"{label}: target depth (m)", dict(cmap="viridis", vmin=lo, vmax=hi)),
            (row[2], diff_mm, f"{label}: rendered − target (mm), mean |δ| {mean_abs:.2f}",
             dict(cmap="RdBu_r", vmin=-max(lim, 1e-6), vmax=max(lim, 1e-6))),
        ):
            h = ax.imshow(np.ma.masked_invalid(img), interpolation="nearest", **kw)
            ax.set_title(ttl, fontsize=8)
            ax.set_axis_off()
            fig.colorbar(h, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    return fig_to_png(fig)


def colour_bar_png(vmin: float, vmax: float, label: str, cmap: str = "viridis", width: float = 4.0) -> bytes:
    """A horizontal colour bar from vmin to vmax with its label, as PNG bytes (the scale of a colour map)."""
    import matplotlib as mpl

    plt = _plt()
    fig, ax = plt.subplots(figsize=(width, 0.75), layout="constrained")
    fig.colorbar(mpl.cm.ScalarMappable(mpl.colors.Normalize(vmin, vmax), cmap=cmap), cax=ax,
                 orientation="horizontal", label=label)
    return fig_to_png(fig)


def split_panels(img: np.ndarray, n: int) -> list[np.ndarray]:
    """The n side-by-side panels of a frame image (renders/: rendered | target | |difference|, n = 3;
    material/renders/: re-render | target, n = 2)."""
    w = img.shape[1] // n
    return [img[:, i * w:(i + 1) * w, :3] for i in range(n)]


def abs_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a − b| averaged over the colour channels (0 = equal, 1 = black against white)."""
    return np.abs(a[:, :, :3].astype(np.float32) - b[:, :, :3].astype(np.float32)).mean(axis=2)


def difference_scale(diffs: list[np.ndarray]) -> float:
    """Top of the difference colour scale: the 99th percentile over all pixels that differ at all, at least
    0.02, so the map shows where the error is instead of a few outliers."""
    vals = np.concatenate([d[d > 1e-3].ravel() for d in diffs]) if diffs else np.zeros(0)
    return max(float(np.percentile(vals, 99)), 0.02) if vals.size else 0.02


def comparison_figure(rows: list[tuple[str, np.ndarray, np.ndarray]], first: str = "rendered",
                      cmap: str = "magma") -> bytes:
    """One row per frame: labelled panels `first | target | |difference|`, the difference as a colour map
    on one scale shared by all rows, with its colour bar."""
    plt = _plt()
    diffs = [abs_difference(r, t) for _, r, t in rows]
    vmax = difference_scale(diffs)
    h, w = rows[0][1].shape[:2]
    fig, axes = plt.subplots(len(rows), 3, figsize=(9.6, len(rows) * 3.0 * h / w + 0.9), squeeze=False,
                             layout="constrained")
    image = None
    for ax_row, (label, rendered, target), diff in zip(axes, rows, diffs):
        for ax, img, title in ((ax_row[0], rendered, f"{label}: {first}"), (ax_row[1], target, f"{label}: target"),
                               (ax_row[2], diff, f"{label}: |difference|, mean {diff.mean():.3f}")):
            if img.ndim == 2:
                image = ax.imshow(img, cmap=cmap, vmin=0.0, vmax=vmax, interpolation="nearest")
            else:
                ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
    fig.colorbar(image, ax=axes[:, 2].tolist(), orientation="horizontal", fraction=0.06, pad=0.02,
                 label="|difference| (mean over R, G, B; 1 = black vs white)")
    return fig_to_png(fig)


def strip_figure(frames: list[tuple[str, np.ndarray]], title: str) -> bytes:
    """Frames side by side in one row, each labelled (the novel view through time)."""
    plt = _plt()
    h, w = frames[0][1].shape[:2]
    fig, axes = plt.subplots(1, len(frames), figsize=(1.9 * len(frames), 1.9 * h / w + 0.6), squeeze=False,
                             layout="constrained")
    for ax, (label, img) in zip(axes[0], frames):
        ax.imshow(np.clip(img[:, :, :3], 0, 1), interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    return fig_to_png(fig)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of two [0, 1] images, over the pixels of `mask` (all without one)."""
    err = (a[:, :, :3].astype(np.float64) - b[:, :, :3].astype(np.float64)) ** 2
    err = err[mask] if mask is not None else err.reshape(-1, 3)
    mse = float(err.mean()) if err.size else float("nan")
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
