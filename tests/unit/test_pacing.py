"""Pacing arithmetic with an injected clock: the uplink token bucket (burst, rate, debt queueing,
refill capped at the burst), the frame pacer (fixed grid, no catch-up burst) and the timeline
pacer (a recording's own times, the same rule for late frames)."""

from __future__ import annotations

import threading

import pytest

from robotd.frame_path.pacing import BITS_PER_BYTE, FramePacer, TimelinePacer, TokenBucket


class FakeClock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


def test_burst_passes_at_once_then_bytes_wait_for_the_rate() -> None:
    clock = FakeClock()
    bucket = TokenBucket(1000.0, 500.0, clock=clock)
    assert bucket.reserve(500) == 0.0
    assert bucket.reserve(1000) == pytest.approx(1.0)
    # Debt queues: the next 500 bytes leave after the 1000 before them.
    assert bucket.reserve(500) == pytest.approx(1.5)
    clock.advance(1.5)
    assert bucket.tokens == pytest.approx(0.0)
    assert bucket.reserve(250) == pytest.approx(0.25)


def test_refill_is_capped_at_the_burst() -> None:
    clock = FakeClock()
    bucket = TokenBucket(1000.0, 500.0, clock=clock)
    bucket.reserve(500)
    clock.advance(60.0)  # idle for a minute: still only a burst's worth
    assert bucket.tokens == pytest.approx(500.0)
    assert bucket.reserve(700) == pytest.approx(0.2)


def test_delay_for_does_not_reserve() -> None:
    clock = FakeClock()
    bucket = TokenBucket(1000.0, 0.0, clock=clock)
    assert bucket.delay_for(300) == pytest.approx(0.3)
    assert bucket.delay_for(300) == pytest.approx(0.3)
    assert bucket.reserve(300) == pytest.approx(0.3)
    assert bucket.delay_for(100) == pytest.approx(0.4)


def test_mbit_rate_gives_transfer_time_of_a_link() -> None:
    clock = FakeClock()
    bucket = TokenBucket.from_mbit(2.0, burst_bytes=0, clock=clock)
    one_mb = 1_000_000
    # 1 MB at 2 Mbit/s: 8 Mbit / 2 Mbit/s = 4 s.
    assert bucket.reserve(one_mb) == pytest.approx(one_mb * BITS_PER_BYTE / 2e6)
    assert bucket.rate_bytes_per_s == pytest.approx(250_000.0)


@pytest.mark.parametrize(("rate", "burst"), [(0.0, 10.0), (-1.0, 10.0), (1.0, -5.0)])
def test_bad_bucket_settings_are_refused(rate: float, burst: float) -> None:
    with pytest.raises(ValueError, match="must be"):
        TokenBucket(rate, burst)


def test_negative_reservation_is_refused() -> None:
    with pytest.raises(ValueError, match="negative"):
        TokenBucket(1.0, 1.0).reserve(-1)


def test_frame_pacer_keeps_a_fixed_grid() -> None:
    clock = FakeClock()
    pacer = FramePacer(10.0, clock=clock)  # 100 ms period
    assert pacer.delay() == 0.0  # the first frame starts at once
    clock.advance(0.03)  # a 30 ms frame
    assert pacer.delay() == pytest.approx(0.07)
    clock.advance(0.07 + 0.05)  # waited, then a 50 ms frame
    assert pacer.delay() == pytest.approx(0.05)


def test_frame_pacer_restarts_the_grid_instead_of_bursting() -> None:
    clock = FakeClock()
    pacer = FramePacer(10.0, clock=clock)
    pacer.delay()
    clock.advance(0.35)  # a frame 2.5 periods long
    assert pacer.delay() == 0.0
    clock.advance(0.01)
    # The grid restarted at the late frame: the next start is a period after it, not at once.
    assert pacer.delay() == pytest.approx(0.09)


def test_frame_pacer_without_fps_never_waits() -> None:
    clock = FakeClock()
    pacer = FramePacer(None, clock=clock)
    assert [pacer.delay() for _ in range(3)] == [0.0, 0.0, 0.0]


def test_frame_pacer_wait_gives_up_when_stopped() -> None:
    stop = threading.Event()
    stop.set()
    assert FramePacer(None).wait(stop) is False
    assert FramePacer(1e-3).wait(threading.Event()) is True


def test_the_timeline_pacer_starts_frames_at_the_recorded_offsets() -> None:
    clock = FakeClock()
    offsets = iter([0.0, 0.05, 0.15, 0.16, None])
    pacer = TimelinePacer(lambda: next(offsets), clock=clock)
    assert pacer.delay() == 0.0  # the first frame starts at once
    clock.advance(0.01)  # the frame took 10 ms
    assert pacer.delay() == pytest.approx(0.04)
    clock.advance(0.04 + 0.02)
    assert pacer.delay() == pytest.approx(0.08)  # a gap of 100 ms in the recording
    clock.advance(0.08)
    assert pacer.delay() == pytest.approx(0.01)
    clock.advance(0.01)
    assert pacer.delay() == 0.0  # the source has ended: its read says so


def test_the_timeline_pacer_moves_on_after_a_slow_frame_instead_of_bursting() -> None:
    clock = FakeClock()
    offsets = iter([0.0, 0.1, 0.2, 0.3, 0.4])
    pacer = TimelinePacer(lambda: next(offsets), clock=clock)
    pacer.delay()
    clock.advance(0.5)  # a frame took 5 gaps: the next starts now, not in a burst of four
    assert pacer.delay() == 0.0
    clock.advance(0.01)
    assert pacer.delay() == pytest.approx(0.09)
    clock.advance(0.09 + 0.15)  # 50 ms late, less than a gap: the timeline holds
    assert pacer.delay() == 0.0
    clock.advance(0.01)
    assert pacer.delay() == pytest.approx(0.04)  # offset 0.4 is due at 0.8 s on the old line
