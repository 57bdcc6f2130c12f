"""The shape phase's frame schedule: the fixed one, and the one that waits for the newest frame to converge."""

import pytest

from saft.reconstruct.config import ShapeConfig, shape_schedule
from saft.reconstruct.frame_schedule import FrameSchedule


def _run(sched: FrameSchedule, loss_fn) -> list[int]:
    frames = []
    while not sched.done:
        frames.append(sched.frames)
        sched.epoch_done(loss_fn(sched, len(frames)))
        assert len(frames) < 10_000
    return frames


@pytest.mark.parametrize("n,cfg", [(50, ShapeConfig()), (2, ShapeConfig()), (3, ShapeConfig()),
                                   (10, ShapeConfig(initial_frames=1, initial_epochs=7, add_frame_every=2,
                                                    final_epochs=4)),
                                   (6, ShapeConfig(final_epochs=0))])
def test_without_plateau_it_is_the_fixed_schedule(n, cfg):
    assert _run(FrameSchedule(n, cfg), lambda s, k: 1.0 / k) == shape_schedule(n, cfg)


def test_a_frame_waits_while_its_loss_falls_and_moves_on_at_a_plateau():
    cfg = ShapeConfig(add_frame_every=5, final_epochs=3, plateau_max_extra=4, plateau_tol=0.02)
    falling = _run(FrameSchedule(6, cfg), lambda s, k: 0.5 ** k)        # always improving: every extra epoch
    assert falling == [3] * 9 + [4] * 9 + [5] * 9 + [6] * 3
    flat = _run(FrameSchedule(6, cfg), lambda s, k: 1.0)                # no progress: the fixed schedule
    assert flat == shape_schedule(6, cfg)
    s = FrameSchedule(6, cfg)
    _run(s, lambda s_, k: 0.5 ** k)
    assert s.extra_total == 12 and s.total_epochs == len(shape_schedule(6, cfg)) + 12


def test_restore_continues_where_a_checkpoint_left_off():
    cfg = ShapeConfig(add_frame_every=3, final_epochs=4, plateau_max_extra=2)
    loss = lambda s, k: 1.0 / (1 + k % 7)                               # noqa: E731
    full = _run(FrameSchedule(8, cfg), loss)
    s = FrameSchedule(8, cfg)
    head = []
    for k in range(1, 12):
        head.append(s.frames)
        s.epoch_done(loss(s, k))
    resumed = FrameSchedule.restore(8, cfg, s.state_dict(), len(head))
    tail = []
    while not resumed.done:
        tail.append(resumed.frames)
        resumed.epoch_done(loss(resumed, len(head) + len(tail)))
    assert head + tail == full


@pytest.mark.parametrize("epoch", [0, 1, 4, 5, 17, 60, 261])
def test_old_checkpoints_without_schedule_state_resume_on_the_fixed_schedule(epoch):
    cfg = ShapeConfig()
    fixed = shape_schedule(50, cfg)
    s = FrameSchedule.restore(50, cfg, None, epoch)
    assert _run(s, lambda s_, k: 1.0) == fixed[epoch:]


def test_simulated_frames_per_epoch_counts_the_windowed_work():
    from saft.reconstruct.frame_schedule import simulated_frames_per_epoch, window_first_frame

    full = ShapeConfig(window=0)
    assert simulated_frames_per_epoch(40, full) == shape_schedule(40, full)
    cfg = ShapeConfig(window=6, full_pass_every=10, final_epochs=24)
    sched = shape_schedule(40, cfg)
    work = simulated_frames_per_epoch(40, cfg)
    assert len(work) == len(sched)
    for epoch, (f, n) in enumerate(zip(sched, work)):
        if f >= 40 or epoch % 10 == 0 or f <= 7:   # final epochs, full passes, frames within the window
            assert n == f
        else:                                      # the window and the state it starts from
            assert n == 7 == f - window_first_frame(f, epoch, False, cfg)
    assert sum(work) < 0.6 * sum(sched)
