"""Resume state of a run: written atomically at epoch boundaries; Ctrl-C waits for the epoch to end.

A checkpoint is one torch file, DIR/checkpoint/state.pt, holding the phase, the epoch, every parameter,
every optimizer state, the random state and the log so far. Because it is only written between two
epochs, a resumed run repeats exactly what the uninterrupted run would have done (CPU, same seed).
"""

from __future__ import annotations

import signal
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from saft.io_utils import atomic_path

CHECKPOINT = Path("checkpoint") / "state.pt"


def checkpoint_path(out_dir: Path) -> Path:
    return Path(out_dir) / CHECKPOINT


def save_checkpoint(out_dir: Path, state: dict) -> None:
    with atomic_path(checkpoint_path(out_dir)) as tmp:
        torch.save(state, tmp)


def load_checkpoint(out_dir: Path) -> dict | None:
    path = checkpoint_path(out_dir)
    if not path.is_file():
        return None
    return torch.load(path, map_location="cpu", weights_only=False)


class Interrupted(Exception):
    """Raised at an epoch boundary after Ctrl-C, once the checkpoint is written."""


class InterruptGuard:
    """Turns SIGINT into a flag that the epoch loop checks at its end (a second Ctrl-C aborts at once)."""

    def __init__(self):
        self.requested = False

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    @contextmanager
    def active(self) -> Iterator["InterruptGuard"]:
        try:
            previous = signal.signal(signal.SIGINT, self._handler)
        except ValueError:  # not in the main thread: no signal handling
            yield self
            return
        try:
            yield self
        finally:
            signal.signal(signal.SIGINT, previous)


class CheckpointClock:
    """Decides when to write: at most every `seconds`, always when forced."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.last = time.monotonic()

    def due(self) -> bool:
        return time.monotonic() - self.last >= self.seconds

    def mark(self) -> None:
        self.last = time.monotonic()
