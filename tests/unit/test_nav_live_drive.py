"""A maneuver driven in clock time (`nav.live_drive`) and its frame source
(`stereo:maneuver:N`, `nav.maneuver_source`), fed by a fake result feeder instead of a daemon.

The deterministic parts: the drive stepped by hand at chosen clock times (the unicycle's
kinematics, a late controller caught up in sub-steps, the start at the first d_coll, collisions,
the end at the script's duration, results applied in order), the outcome file, and the source's
spec, frames and end of stream. One test runs the control thread on the real clock with a short
script and waits for its end (an event, not a sleep)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from common.errors import UserError
from common.source_spec import SourceError
from nav.closed_loop import Maneuver
from nav.curvature import CurvatureBins, DcollProfile
from nav.live_drive import (
    OUTCOME_FORMAT,
    DriveOutcome,
    LiveDrive,
    ManeuverDrive,
    read_outcome,
    write_outcome,
)
from nav.maneuver_source import DCOLL_OUTPUT, StereoManeuverSource
from nav.maneuvers import circuit_lap
from nav.render import Pose
from nav.shared_control import AssistantParams, Command
from nav.world import corridor_with_wall
from robotd.frame_path.frame import FrameResult
from robotd.sources.frame_sources import EndOfStream
from robotd.sources.opening import open_source
from robotd.sources.stereo_frame import STEREO_VIEWS, StereoFrame

NORTH = math.pi / 2
FULL_SPEED_MPS = 0.4
WALL_M = 1.2
ROBOT_RADIUS_M = 0.2
PERIOD_S = 0.02
T0 = 100.0
"""An arbitrary clock origin: the drive works in the clock's own seconds."""
STOP_MARGIN_M = 0.45
LATENCY_S = 0.1
H, W = 60, 80
END_WAIT_S = 10.0


def straight_at_wall(duration_s: float = 4.0) -> Maneuver:
    return Maneuver(
        "straight", Pose(0.0, 0.0, NORTH), lambda t: Command(FULL_SPEED_MPS, 0.0), duration_s
    )


def drive(assisted: bool, duration_s: float = 4.0) -> ManeuverDrive:
    return ManeuverDrive(
        corridor_with_wall(WALL_M),
        straight_at_wall(duration_s),
        assisted=assisted,
        params=AssistantParams(stop_margin_m=STOP_MARGIN_M),
    )


def wall_profile(y_m: float) -> DcollProfile:
    """What a perfect camera at y sees of the wall: the same free arc straight ahead in every
    bin (conservative for the curved ones)."""
    bins = CurvatureBins()
    return DcollProfile.from_bins(bins, np.full(bins.count, WALL_M - y_m))


def run_with_feeder(d: ManeuverDrive, until_s: float) -> None:
    """Control every period from T0; a frame every 0.1 s whose d_coll arrives LATENCY_S later."""
    pending: list[tuple[float, float, float]] = []  # (arrival, capture time, y at capture)
    d.observe(wall_profile(0.0), T0 - LATENCY_S, T0)
    for k in range(round(until_s / PERIOD_S) + 1):
        t = T0 + k * PERIOD_S
        if k % 5 == 0:
            pose = d.capture(t)
            if pose is not None:
                pending.append((t + LATENCY_S, t, pose.y))
        while pending and pending[0][0] <= t + 1e-9:
            _, t_frame, y = pending.pop(0)
            d.observe(wall_profile(y), t_frame, t)
        d.step_control(t)
        if d.ended:
            return


def test_the_robot_stands_until_the_first_dcoll_starts_the_maneuver() -> None:
    d = drive(assisted=False)
    assert d.capture(T0) == Pose(0.0, 0.0, NORTH)
    d.step_control(T0 + 5.0)  # no result yet: no script, no motion, however long
    assert d.capture(T0 + 5.0) == Pose(0.0, 0.0, NORTH)
    assert not d.started and not d.ended and d.frames_read == 2
    assert not d.observe(wall_profile(0.0), T0 + 4.9, T0 + 5.0)  # off: started, not applied
    assert d.t0 == T0 + 5.0


def test_kinematics_full_speed_from_rest_under_the_paper_limits() -> None:
    d = drive(assisted=False)
    d.observe(wall_profile(0.0), T0, T0)
    for k in range(51):
        d.step_control(T0 + k * PERIOD_S)
    # 0.4 m/s after 0.05 s at a_max = 8 m/s²: 0.4·1 − 0.4²/(2·8) = 0.39 m in 1 s, less 0.4 mm
    # as the unicycle integrates speed per 20 ms step (the third step ramps 0.32 → 0.4 over it)
    pose = d.robot.pose
    assert pose.y == pytest.approx(0.3896, abs=1e-9) and pose.x == pytest.approx(0.0, abs=1e-12)
    assert d.distance_m == pytest.approx(0.3896, abs=1e-9)


def test_a_late_controller_is_caught_up_in_sub_steps() -> None:
    """Regression: a control thread woken late must not teleport the robot or skip the
    collision check; the unicycle moves under the last command for the time that passed."""
    on_time, late = drive(assisted=False), drive(assisted=False)
    for d in (on_time, late):
        d.observe(wall_profile(0.0), T0, T0)
        d.step_control(T0)
    for k in range(1, 26):
        on_time.advance(T0 + k * PERIOD_S)
    late.advance(T0 + 0.5)  # one wake, half a second late
    assert late.robot.pose.y == pytest.approx(on_time.robot.pose.y, abs=1e-9)
    far = drive(assisted=False)
    far.observe(wall_profile(0.0), T0, T0)
    far.step_control(T0)
    far.advance(T0 + 3.5)  # asleep past the wall: the collision is still found on the way
    assert far.ended and far.collision_s == pytest.approx(2.525, abs=PERIOD_S)
    assert far.robot.pose.y < WALL_M - ROBOT_RADIUS_M + FULL_SPEED_MPS * PERIOD_S


def test_unassisted_drives_into_the_wall_and_the_source_ends() -> None:
    d = drive(assisted=False)
    run_with_feeder(d, 4.0)
    out = d.outcome()
    # the robot's circle touches the wall after 1.0 m: 0.4·t − 0.01 = 1.0 at t = 2.525 s
    assert out.collided and out.collision_s == pytest.approx(2.525, abs=PERIOD_S)
    assert out.min_clearance_m <= 0 and out.frames_applied == 0
    assert out.mean_dcoll_age_s is None
    assert d.capture(T0 + 3.0) is None  # over: no more frames


def test_assisted_stops_short_and_ends_at_the_script_duration() -> None:
    d = drive(assisted=True, duration_s=4.0)
    run_with_feeder(d, 5.0)
    out = d.outcome()
    assert not out.collided and out.collision_s is None
    assert out.driven_s == pytest.approx(4.0)
    # stopped STOP_MARGIN_M short of the wall (the margin counts from the axle)
    assert out.min_clearance_m == pytest.approx(STOP_MARGIN_M - ROBOT_RADIUS_M, abs=0.02)
    assert out.distance_m == pytest.approx(WALL_M - STOP_MARGIN_M, abs=0.02)
    # frames at 0, 0.1, ... 3.9 s; the first d_coll (taken before the start) and the 39 that
    # arrived before the end applied, the last frame's result came too late
    assert (out.frames_read, out.frames_applied) == (40, 40)
    # a d_coll is LATENCY_S old on arrival and replaced 0.1 s later: 0.14 s on average
    assert out.mean_dcoll_age_s == pytest.approx(LATENCY_S + 0.04)


def test_an_older_result_than_the_one_held_is_not_applied() -> None:
    d = drive(assisted=True)
    assert d.observe(wall_profile(0.0), T0 - 0.1, T0)
    assert not d.observe(wall_profile(0.0), T0 - 0.2, T0 + 0.02)
    assert d.observe(wall_profile(0.0), T0 - 0.05, T0 + 0.04)
    assert d.frames_applied == 2


def test_outcome_file_is_one_json_line_read_back(tmp_path: Path) -> None:
    path = tmp_path / "outcome.json"
    outcome = DriveOutcome("m", True, False, None, 0.25, 0.75, 4.0, 40, 39, 0.14, 0.003)
    write_outcome(path, outcome, maneuver_index=1, lap=2)
    lines = path.read_text().splitlines()
    assert len(lines) == 1
    data = read_outcome(path)
    assert data == json.loads(lines[0])
    assert data["format"] == OUTCOME_FORMAT and (data["maneuver_index"], data["lap"]) == (1, 2)
    assert data["frames_applied"] == 39 and data["collision_s"] is None
    assert [p.name for p in tmp_path.iterdir()] == ["outcome.json"]  # no temporary left
    with pytest.raises(UserError, match=r"no maneuver outcome at .*missing\.json"):
        read_outcome(tmp_path / "missing.json")
    path.write_text('{"format": 99}\n')
    with pytest.raises(UserError, match="expected format 1"):
        read_outcome(path)


def test_the_control_thread_ends_the_maneuver_and_reports_once() -> None:
    outcomes: list[DriveOutcome] = []
    live = LiveDrive(drive(assisted=False, duration_s=0.2), outcomes.append)
    assert live.capture() is not None
    live.observe(wall_profile(0.0), 0.0)
    try:
        assert live.ended.wait(END_WAIT_S), "the maneuver did not end"
    finally:
        live.stop()
    assert live.capture() is None
    assert len(outcomes) == 1 and not outcomes[0].collided
    assert outcomes[0].driven_s == pytest.approx(0.2)
    assert outcomes[0].max_control_lag_s >= 0


def test_an_end_found_by_a_frame_capture_is_reported_when_stopped_at_once() -> None:
    """Regression: the robot's source found the end on a capture, the daemon closed it before
    the next control step, and the outcome was never written."""
    now = [T0]
    outcomes: list[DriveOutcome] = []
    live = LiveDrive(drive(assisted=False, duration_s=0.2), outcomes.append, clock=lambda: now[0])
    live.observe(wall_profile(0.0), T0)  # the control thread steps, the clock stands still
    now[0] = T0 + 1.0
    assert live.capture() is None  # the capture ran into the script's end
    live.stop()
    assert live.ended.is_set() and len(outcomes) == 1
    assert outcomes[0].driven_s == pytest.approx(0.2)


def result(frame: int, d_coll: np.ndarray) -> FrameResult:
    return FrameResult(frame, {}, {DCOLL_OUTPUT: d_coll}, None, "robot", False)  # type: ignore[arg-type]


def test_maneuver_source_renders_the_start_pose_and_is_closed_without_an_outcome(
    tmp_path: Path,
) -> None:
    out = tmp_path / "o.json"
    source = open_source(f"stereo:maneuver:1:lap=2:out={out}", height=H, width=W)
    try:
        assert isinstance(source, StereoManeuverSource)
        assert source.views == STEREO_VIEWS and "lap 2" in source.description
        assert source.drive.drive.maneuver.start == circuit_lap(2)[1].maneuver.start
        first, second = source.read(), source.read()
        assert isinstance(first, StereoFrame) and first.views["left"].shape == (H, W, 3)
        # the robot stands still before the first result: the same scene (fresh sensor noise)
        assert np.abs(first.views["left"].astype(int) - second.views["left"]).mean() < 5
        with pytest.raises(SourceError, match="no 'd_coll' output"):
            source.on_result(FrameResult(0, {}, {"x": np.zeros(1)}, None, "robot", False))  # type: ignore[arg-type]
        source.on_result(result(1, np.full((1, CurvatureBins().count), 5.0, np.float32)))
        assert source.drive.drive.started and source.drive.drive.frames_applied == 1
    finally:
        source.close()
    assert not out.exists()  # closed before the maneuver ended


def test_maneuver_source_ends_its_stream_after_the_maneuver(tmp_path: Path) -> None:
    out = tmp_path / "o.json"
    source = open_source(f"stereo:maneuver:0:assist=off:out={out}", height=H, width=W)
    assert isinstance(source, StereoManeuverSource)
    source.read()
    # stand in for the control thread: the script's end, stepped by hand on the source's drive
    d = source.drive.drive
    d.observe(wall_profile(0.0), 0.0, 0.0)
    d.advance(d.end_at)
    with pytest.raises(EndOfStream, match="the maneuver is over"):
        source.read()
    source.close()


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("stereo:maneuver", "expected stereo:maneuver:N"),
        ("stereo:maneuver:x", "expected stereo:maneuver:N"),
        ("stereo:maneuver:7", "maneuver must be 0..6"),
        ("stereo:maneuver:1:lap=-1", "lap='-1' is not a lap number"),
        ("stereo:maneuver:1:assist=maybe", "assist='maybe'; expected on or off"),
        ("stereo:maneuver:1:speed=2", "unknown option 'speed'; known: lap, assist, out"),
        ("stereo:maneuver:1:lap", "expected name=value options"),
        ("stereo:maneuver:1:out=/no/such/dir/o.json", "no directory /no/such/dir"),
    ],
)
def test_bad_maneuver_specs_are_one_line(spec: str, message: str) -> None:
    with pytest.raises(SourceError, match=message):
        open_source(spec, height=H, width=W)
