"""DIR/summary.csv (one row per task) and DIR/summary.html (the paper's table layout) of a batch.

summary.csv: scene, setting, status (done | skipped | failed | interrupted), wall_s, the mean CD2 (1e-4 m²),
CD1 (cm), p2s (mm) and depth δ (cm) from the task's metrics.json when it was evaluated, error, out_dir.
summary.html: per metric a table with the scenes as columns and the settings as rows, the mean over scenes
last, the best (lowest) value of every column in bold.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

from saft.batch.plan import BatchTask
from saft.evaluate import CD1, CD2, DEPTH, METRIC_LABELS, P2S_L1
from saft.io_utils import atomic_write_text

# (metrics.json key, csv column, readable name with its unit)
METRICS = ((CD2, "cd2_1e-4m2", METRIC_LABELS[CD2]), (CD1, "cd1_cm", METRIC_LABELS[CD1]),
           (P2S_L1, "p2s_mm", METRIC_LABELS[P2S_L1]), (DEPTH, "depth_cm", METRIC_LABELS[DEPTH]))
CSV_FIELDS = ["scene", "setting", "status", "wall_s", *(col for _, col, _ in METRICS), "error", "out_dir"]


@dataclass
class TaskOutcome:
    task: BatchTask
    status: str                 # done | skipped | failed | interrupted
    wall_s: float
    error: str = ""
    resumed: bool = False

    @property
    def ok(self) -> bool:
        return self.status in ("done", "skipped")

    def metrics(self) -> dict[str, float]:
        """Mean metrics of the result (metrics.json), {} when it was not evaluated."""
        path = self.task.out_dir / "metrics.json"
        if not self.ok or not path.is_file():
            return {}
        try:
            mean = json.loads(path.read_text()).get("mean", {})
        except (OSError, json.JSONDecodeError):
            return {}
        out = {}
        for key, col, _ in METRICS:
            v = mean.get(key)
            if isinstance(v, (int, float)) and math.isfinite(v):
                out[col] = float(v)
        return out


def summary_rows(outcomes: list[TaskOutcome]) -> list[dict]:
    rows = []
    for o in outcomes:
        m = o.metrics()
        rows.append({"scene": o.task.scene_name, "setting": o.task.setting, "status": o.status,
                     "wall_s": f"{o.wall_s:.1f}", **{col: (f"{m[col]:.6g}" if col in m else "") for _, col, _ in METRICS},
                     "error": o.error, "out_dir": str(o.task.out_dir)})
    return rows


def summary_csv(outcomes: list[TaskOutcome]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    w.writerows(summary_rows(outcomes))
    return buf.getvalue()


def _metric_table(outcomes: list[TaskOutcome], col: str, title: str, scenes: list[str], settings: list[str]) -> str:
    value = {(o.task.setting, o.task.scene_name): o.metrics().get(col) for o in outcomes}
    status = {(o.task.setting, o.task.scene_name): o.status for o in outcomes}
    grid = {s: [value.get((s, sc)) for sc in scenes] for s in settings}
    for s in settings:  # the mean over scenes, only where every scene has a value
        vals = grid[s]
        grid[s].append(sum(vals) / len(vals) if vals and all(v is not None for v in vals) else None)
    columns = scenes + ["mean"]
    best = []
    for j in range(len(columns)):
        vals = [grid[s][j] for s in settings if grid[s][j] is not None]
        best.append(min(vals) if vals else None)
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = ""
    for s in settings:
        cells = ""
        for j, v in enumerate(grid[s]):
            if v is None:
                st = status.get((s, columns[j]), "") if j < len(scenes) else ""
                cells += f'<td class="none">{html.escape(st if st and st not in ("done", "skipped") else "—")}</td>'
            else:
                text = f"{v:.3f}"
                cells += f"<td><b>{text}</b></td>" if len(settings) > 1 and v == best[j] else f"<td>{text}</td>"
        body += f"<tr><th>{html.escape(s or 'default')}</th>{cells}</tr>"
    return (f"<h2>{html.escape(title)}</h2><table><tr><th>setting</th>{head}</tr>{body}</table>")


def summary_html(outcomes: list[TaskOutcome]) -> str:
    scenes = list(dict.fromkeys(o.task.scene_name for o in outcomes))
    settings = list(dict.fromkeys(o.task.setting for o in outcomes))
    tables = [_metric_table(outcomes, col, title, scenes, settings) for _, col, title in METRICS
              if any(col in o.metrics() for o in outcomes)]
    if not tables:
        tables.append("<p>No task was evaluated against ground truth (run with --gt for metric tables).</p>")
    counts = {}
    for o in outcomes:
        counts[o.status] = counts.get(o.status, 0) + 1
    status_rows = "".join(
        f"<tr><td>{html.escape(o.task.scene_name)}</td><td>{html.escape(o.task.setting or 'default')}</td>"
        f"<td>{html.escape(o.status)}</td><td>{o.wall_s:.1f}</td><td>{html.escape(o.error)}</td></tr>"
        for o in outcomes)
    css = ("body{font-family:system-ui,sans-serif;margin:24px;color:#222}table{border-collapse:collapse;"
           "margin-bottom:18px}td,th{border:1px solid #bbb;padding:3px 10px;text-align:right}"
           "th{background:#eef1f5}td.none{color:#999;text-align:center}h2{font-size:1.1em}")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><link rel=\"icon\" href=\"data:,\">"
            f"<title>saft batch summary</title><style>{css}</style></head><body><h1>saft batch</h1>"
            f"<p>{len(outcomes)} tasks: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) +
            ". Lower is better; the best value of each column in bold; mean = mean over the scenes.</p>"
            + "".join(tables) +
            "<h2>Tasks</h2><table><tr><th>scene</th><th>setting</th><th>status</th><th>wall (s)</th><th>error</th>"
            f"</tr>{status_rows}</table></body></html>\n")


def write_summary(batch_dir: Path, outcomes: list[TaskOutcome]) -> tuple[Path, Path]:
    csv_path, html_path = Path(batch_dir) / "summary.csv", Path(batch_dir) / "summary.html"
    atomic_write_text(csv_path, summary_csv(outcomes))
    atomic_write_text(html_path, summary_html(outcomes))
    return csv_path, html_path
