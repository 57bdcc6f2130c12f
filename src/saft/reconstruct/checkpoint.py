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

from saft.errors import SaftInputError
from saft.io_utils import atomic_path

CHECKPOINT = Path("checkpoint") / "state.pt"


def checkpoint_path(out_dir: Path) -> Path:
    return Path(out_dir) / CHECKPOINT


def save_checkpoint(out_dir: Path, state: dict) -> None:
    with atomic_path(checkpoint_path(out_dir)) as tmp:
        torch.save(state, tmp)


# What a checkpoint must hold besides "version", "phase", "log", "timings" and "identity", by phase.
PHASE_KEYS = {"texture": (), "shape": ("texture",), "outputs": ("texture", "shape_state", "positions"),
              "appearance": ("texture", "shape_state", "positions"), "done": ("texture", "shape_state", "positions")}


def load_checkpoint(out_dir: Path, version: int | None = None) -> dict | None:
    """The saved state, None without a checkpoint; SaftInputError (naming the file) when it is truncated,
    not a saft checkpoint, from another version (`version`: the one expected) or missing a part."""
    path = checkpoint_path(out_dir)
    if not path.is_file():
        return None
    restart = "remove it or pass --overwrite to start again"
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # truncated zip, garbage, pickle errors: all mean "unusable"
        raise SaftInputError(path, f"cannot read the checkpoint ({type(exc).__name__}; truncated or not a saft "
                                   f"checkpoint); {restart}") from None
    if not isinstance(state, dict) or state.get("phase") not in PHASE_KEYS:
        raise SaftInputError(path, f"not a saft checkpoint; {restart}")
    if version is not None and state.get("version") != version:
        raise SaftInputError(path, f"checkpoint from another saft version ({state.get('version')!r}, this one "
                                   f"writes {version}); {restart}")
    missing = [k for k in ("log", "timings", "identity", *PHASE_KEYS[state["phase"]]) if k not in state]
    if missing:
        raise SaftInputError(path, f"the checkpoint lacks {', '.join(missing)} (damaged); {restart}")
    return state


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
    """Decides when to write: at most every `seconds`, and with `seconds` > 0 never so often that writing takes
    more than SHARE of the run's time (R1's resume state holds the solver's kept factors, 144 MB: written
    every 20 s it cost 5 % of the run); always when forced."""

    SHARE = 0.02

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.last = time.monotonic()
        self.cost = 0.0

    def due(self) -> bool:
        wait = self.seconds if self.seconds <= 0 else max(self.seconds, self.cost / self.SHARE)
        return time.monotonic() - self.last >= wait

    def mark(self, cost: float = 0.0) -> None:
        """A checkpoint was written now, in `cost` seconds."""
        self.last = time.monotonic()
        self.cost = cost
