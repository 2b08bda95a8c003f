"""Latency windows saved a slice per tick (`registry.profile_saver`): a small fleet's changes go
out at each interval in one go, a large one's are spread over the interval's ticks, the longest
unsaved first, and none is left behind."""

from __future__ import annotations

import pytest

from common.wire.telemetry import ProbeReport
from registry.measurements import Measurements
from registry.profile_saver import PacedSaver
from registry.rib import MEMORY, Rib

TICK_S = 0.1
INTERVAL_S = 1.0  # 10 ticks


def measurements_with(windows: int) -> Measurements:
    m = Measurements(5, deadline_s=0.5, timeout_count=3, on_bad_sample=lambda w, p: None)
    for i in range(windows):
        report = ProbeReport(
            robot="robot-1",
            deployment=f"edge-{i:03d}",
            ok=True,
            at=0.0,
            rtt_s=0.05,
            load=0,
            capacity=4,
        )
        m.record_probe_report(report, "ef/unit/probe/robot-1")
    return m


def run_ticks(saver: PacedSaver, start: float, ticks: int) -> list[int]:
    return [saver.tick(start + k * TICK_S) for k in range(ticks)]


def test_a_small_fleet_is_saved_at_each_interval_in_one_go() -> None:
    m = measurements_with(30)
    with Rib(MEMORY) as rib:
        saver = PacedSaver(m, rib, tick_s=TICK_S, interval_s=INTERVAL_S, at_once=50)
        written = run_ticks(saver, 0.0, 11)
        assert written == [0] * 10 + [30], "nothing before the first interval, then all"
        assert m.unsaved == 0 and len(rib.profiles()) == 30


def test_a_large_fleet_is_spread_over_the_ticks_and_all_saved() -> None:
    m = measurements_with(95)
    with Rib(MEMORY) as rib:
        saver = PacedSaver(m, rib, tick_s=TICK_S, interval_s=INTERVAL_S, at_once=50)
        written = run_ticks(saver, 0.0, 21)
        assert written[:10] == [0] * 10
        assert written[10:20] == [10] * 9 + [5], "a tenth of the 95 per tick"
        assert sum(written) == 95 and m.unsaved == 0 and len(rib.profiles()) == 95


def test_nonsense_settings_are_refused() -> None:
    with Rib(MEMORY) as rib, pytest.raises(ValueError, match="tick_s"):
        PacedSaver(measurements_with(0), rib, tick_s=1.0, interval_s=0.5)
