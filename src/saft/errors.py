"""Errors that the `saft` command reports as one clear line (exit code 2) instead of a traceback."""

from __future__ import annotations

from pathlib import Path


class SaftInputError(Exception):
    """Bad user input: a missing or malformed file, an inconsistent scene, a bad config value.

    The message always names the file (or the config key) and what is wrong with it.
    """

    def __init__(self, where: str | Path | None, problem: str):
        self.where = str(where) if where is not None else None
        self.problem = problem
        super().__init__(f"{self.where}: {problem}" if self.where else problem)


class SimulationError(RuntimeError):
    """The cloth simulation produced NaN or inf (names the frame and the substep)."""


class BackendUnavailableError(RuntimeError):
    """An optional backend (nvdiffrast, Mitsuba, a system LLVM) cannot be loaded; the message says what to install."""
