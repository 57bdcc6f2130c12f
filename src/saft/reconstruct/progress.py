"""Progress display (phase, epoch, frames in use, loss, ETA) and the per-epoch log of a run."""

from __future__ import annotations

import csv
import io
import logging
import time
from pathlib import Path

from saft.io_utils import atomic_write_text

log = logging.getLogger("saft")

LOG_FIELDS = ["phase", "epoch", "frames", "loss", "image", "silhouette", "energy", "force", "track", "held", "smooth",
              "env_l1", "env_smooth", "lr_factor", "backtracks", "seconds"]


class Progress:
    """A rich progress bar per phase (or plain log lines every few seconds with quiet=True)."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self._progress = None
        self._task = None
        self._last_log = 0.0

    def start_phase(self, phase: str, total_epochs: int, start_epoch: int = 0) -> None:
        self.end_phase()
        self.phase = phase
        if self.quiet:
            log.info("phase %s: %d epochs", phase, total_epochs)
            return
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress as RichProgress, TextColumn,
                                   TimeElapsedColumn, TimeRemainingColumn)

        self._progress = RichProgress(
            TextColumn("[bold]{task.description:<10}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("frames {task.fields[frames]:>3}"), TextColumn("loss {task.fields[loss]}"),
            TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), transient=False)
        self._progress.start()
        self._task = self._progress.add_task(phase, total=total_epochs, completed=start_epoch, frames="-", loss="-")

    def update(self, epoch: int, frames: int, loss: float, total: int | None = None) -> None:
        """total: the phase's epoch count when it has changed (a schedule that waits for convergence)."""
        if self._progress is not None:
            extra = {} if total is None else {"total": total}
            self._progress.update(self._task, completed=epoch + 1, frames=frames, loss=f"{loss:.4e}", **extra)
        elif self.quiet and time.monotonic() - self._last_log > 30:
            self._last_log = time.monotonic()
            log.info("%s epoch %d frames %d loss %.4e", self.phase, epoch + 1, frames, loss)

    def end_phase(self) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None


class EpochLog:
    """Rows of log.csv; kept in memory (and in the checkpoint) and rewritten atomically."""

    def __init__(self, rows: list[dict] | None = None):
        self.rows: list[dict] = list(rows or [])

    def add(self, **row) -> None:
        self.rows.append({k: row.get(k, "") for k in LOG_FIELDS})

    def write(self, path: Path) -> None:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=LOG_FIELDS)
        w.writeheader()
        for r in self.rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
        atomic_write_text(path, buf.getvalue())
