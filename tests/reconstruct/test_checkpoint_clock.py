"""The checkpoint clock: at most every `seconds`, and never so often that writing dominates the run."""

from __future__ import annotations

import saft.reconstruct.checkpoint as checkpoint
from saft.reconstruct.checkpoint import CheckpointClock


def _clock_at(monkeypatch, seconds: float):
    now = [100.0]
    monkeypatch.setattr(checkpoint.time, "monotonic", lambda: now[0])
    return CheckpointClock(seconds), now


def test_a_cheap_checkpoint_is_due_after_the_interval(monkeypatch):
    clock, now = _clock_at(monkeypatch, 20.0)
    clock.mark(0.01)
    now[0] += 19.9
    assert not clock.due()
    now[0] += 0.2
    assert clock.due()


def test_a_costly_checkpoint_waits_until_its_cost_is_a_small_share(monkeypatch):
    clock, now = _clock_at(monkeypatch, 20.0)
    clock.mark(1.0)                                # 1 s to write: due after 1 / SHARE = 50 s, not 20
    now[0] += 49.0
    assert not clock.due()
    now[0] += 1.5
    assert clock.due()


def test_zero_seconds_writes_after_every_epoch_whatever_it_costs(monkeypatch):
    clock, now = _clock_at(monkeypatch, 0.0)
    clock.mark(5.0)
    assert clock.due()
