"""The checkpoint clock: at most every `seconds`, and never so often that writing dominates the run."""

from __future__ import annotations

import pytest

import saft.reconstruct.checkpoint as checkpoint
from saft.reconstruct.checkpoint import CheckpointClock


def _clock_at(monkeypatch, seconds: float):
    now = [100.0]
    monkeypatch.setattr(checkpoint.time, "monotonic", lambda: now[0])
    return CheckpointClock(seconds), now


@pytest.mark.parametrize("cost, quiet_until, due_at", [
    (0.01, 19.9, 20.1),   # a cheap checkpoint: due after the interval
    (1.0, 49.0, 50.5),    # 1 s to write: due after 1 / SHARE = 50 s, not 20
])
def test_a_checkpoint_is_due_after_the_interval_or_when_its_cost_is_a_small_share(monkeypatch, cost, quiet_until,
                                                                                    due_at):
    clock, now = _clock_at(monkeypatch, 20.0)
    clock.mark(cost)
    now[0] += quiet_until
    assert not clock.due()
    now[0] += due_at - quiet_until
    assert clock.due()


def test_zero_seconds_writes_after_every_epoch_whatever_it_costs(monkeypatch):
    clock, now = _clock_at(monkeypatch, 0.0)
    clock.mark(5.0)
    assert clock.due()
