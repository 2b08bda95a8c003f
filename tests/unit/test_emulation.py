"""The robot's run-time emulation (robotd/emulation.py) with an injected clock: the slowdown
stretches a run to F× its measured time and stops waiting when the run is cancelled or the
robot stops; phases switch the slowdown and the emulated uplink at their first frame; the
startup profile is scaled like the runs; the `--phases` file is validated."""

from __future__ import annotations

import threading
from pathlib import Path

import onnxruntime as ort
import pytest

from common.errors import UserError
from robotd.emulation import (
    EMULATED_LINK_BURST_BYTES,
    Emulation,
    Phase,
    Slowdown,
    load_phases,
    robot_class,
    scaled_profile,
)
from robotd.frame_path.pacing import TokenBucket


class FakeTime:
    """A clock the run and the waits move: `stop.wait(t)` advances it by t (nobody sets it)."""

    def __init__(self) -> None:
        self.now = 10.0
        self.waits: list[float] = []

    def __call__(self) -> float:
        return self.now


class AdvancingEvent(threading.Event):
    def __init__(self, clock: FakeTime) -> None:
        super().__init__()
        self.clock = clock

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None
        self.clock.waits.append(timeout)
        self.clock.now += timeout
        return self.is_set()


def run_taking(clock: FakeTime, seconds: float, options: ort.RunOptions | None = None):
    def fn(opts: ort.RunOptions | None) -> str:
        assert opts is options
        clock.now += seconds
        return "outputs"

    return fn


def test_a_run_takes_factor_times_its_measured_time() -> None:
    clock = FakeTime()
    slow = Slowdown(4.0, stop=AdvancingEvent(clock), clock=clock)
    start = clock.now
    assert slow.run(run_taking(clock, 0.05), None) == "outputs"
    assert clock.now - start == pytest.approx(4 * 0.05)
    assert clock.waits == [pytest.approx(0.15)]  # one wait: nothing to cancel it early


def test_factor_one_adds_no_wait_and_bad_factors_are_refused() -> None:
    clock = FakeTime()
    slow = Slowdown(1.0, stop=AdvancingEvent(clock), clock=clock)
    slow.run(run_taking(clock, 0.05), None)
    assert clock.waits == []
    with pytest.raises(UserError, match=r"--robot-slowdown 0\.5"):
        slow.factor = 0.5
    with pytest.raises(UserError, match="--robot-slowdown inf"):
        Slowdown(float("inf"))


def test_a_cancelled_run_stops_waiting() -> None:
    clock = FakeTime()
    slow = Slowdown(3.0, stop=AdvancingEvent(clock), clock=clock)
    options = ort.RunOptions()

    def cancelled_meanwhile(opts: ort.RunOptions | None) -> str:
        clock.now += 0.1
        options.terminate = True  # the cloud's reply came first
        return "outputs"

    start = clock.now
    slow.stretched(cancelled_meanwhile)(options)
    assert clock.now - start == pytest.approx(0.1)


def test_a_cancellable_wait_looks_at_the_flag_in_short_slices() -> None:
    clock = FakeTime()
    slow = Slowdown(2.0, stop=AdvancingEvent(clock), clock=clock)
    options = ort.RunOptions()
    slow.run(run_taking(clock, 0.02, options), options)
    assert sum(clock.waits) == pytest.approx(0.02)
    assert max(clock.waits) <= 0.005 + 1e-12


def test_a_stop_ends_the_wait() -> None:
    clock = FakeTime()
    stop = AdvancingEvent(clock)
    stop.set()  # the robot was asked to stop
    slow = Slowdown(10.0, stop=stop, clock=clock)
    options = ort.RunOptions()
    slow.run(run_taking(clock, 0.1, options), options)
    assert clock.waits == [pytest.approx(0.005)]  # one slice, not the 0.9 s owed


def test_phases_switch_slowdown_and_uplink_at_their_first_frame() -> None:
    phases = [
        Phase("good", 0, 3, 20.0, 3.0),
        Phase("bad", 3, 2, 0.2, 3.0),
        Phase("open", 5, 2, None, 1.0),
    ]
    slow = Slowdown(1.0)
    uplinks: list[TokenBucket | None] = []
    emulation = Emulation(phases, slow, uplinks.append)
    names = [emulation.enter(n) for n in range(9)]
    assert names == ["good"] * 3 + ["bad"] * 2 + ["open"] * 4  # the last phase holds
    assert len(uplinks) == 3  # applied once per phase
    good, bad, off = uplinks
    assert good is bad is not None  # one link: queued requests keep their place
    assert good.rate_bytes_per_s == pytest.approx(0.2e6 / 8)
    assert good.burst_bytes == EMULATED_LINK_BURST_BYTES
    assert off is None
    assert slow.factor == 1.0
    assert emulation.phase_name(4) == "bad" and emulation.phase_name(100) == "open"


def test_without_phases_nothing_is_switched() -> None:
    uplinks: list[TokenBucket | None] = []
    emulation = Emulation([], Slowdown(2.0), uplinks.append)
    assert emulation.enter(0) is None and emulation.phase_name(5) is None
    assert uplinks == []


def test_set_rate_counts_what_was_queued_at_the_old_rate() -> None:
    clock = FakeTime()
    bucket = TokenBucket(1000.0, 0.0, clock=clock)
    assert bucket.reserve(1000) == pytest.approx(1.0)
    clock.now += 0.5  # half the debt went through at 1000 B/s
    bucket.set_rate(250.0)
    assert bucket.tokens == pytest.approx(-500.0)
    assert bucket.reserve(0) == pytest.approx(2.0)  # the rest now drains at 250 B/s
    with pytest.raises(ValueError, match="positive"):
        bucket.set_rate(0.0)


def test_the_profile_is_scaled_like_the_runs() -> None:
    profile = {
        "digest": "d",
        "full_ms": 20.0,
        "cuts": [{"index": 0, "bytes": 10, "prefix_ms": 0.0, "suffix_ms": 20.0, "codecs": []}],
    }
    scaled = scaled_profile(profile, 3.0)
    assert scaled["full_ms"] == 60.0
    assert scaled["cuts"][0]["suffix_ms"] == 60.0 and scaled["cuts"][0]["bytes"] == 10
    assert profile["full_ms"] == 20.0  # the measured one is left as it was
    assert scaled_profile(profile, 1.0) is profile


def test_robot_classes_grow_with_the_factor() -> None:
    assert robot_class(1.0) == "as fast as this host"
    assert "Raspberry Pi" in robot_class(3.0)
    assert robot_class(50.0) != robot_class(3.0)


def test_phases_file_resolves_from_the_command_line_values(tmp_path: Path) -> None:
    path = tmp_path / "phases.yaml"
    path.write_text("phases:\n  - {name: a, frames: 2}\n  - {name: b, frames: 3, slowdown: 5}\n")
    phases = load_phases(path, uplink_mbit=4.0, slowdown=2.0)
    assert phases == [Phase("a", 0, 2, 4.0, 2.0), Phase("b", 2, 3, 4.0, 5.0)]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("phases:\n  - {name: a, frames: 2, kill_service: true}\n", "kill_service: unknown key"),
        (
            "phases:\n  - name: a\n    frames: 2\n    frames: 3\n",
            "line 4, column 5: duplicate key 'frames', first given on line 3",
        ),
        ("phases: nope\n", "phases: Input should be a valid list"),
        ("[1, 2]\n", "expected a mapping"),
        ("phases:\n  - {name: '', frames: 2}\n", "phases[0].name: String should have at least"),
    ],
)
def test_bad_phases_files_name_the_problem(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "phases.yaml"
    path.write_text(text)
    with pytest.raises(UserError) as caught:
        load_phases(path)
    assert str(caught.value).startswith(f"--phases {path}: ")
    assert expected in str(caught.value)
