"""Recordings in and out, end to end: registry, cloud and robot as real subprocesses on loopback.

What must hold (issue 24 §4): a robot run with `--record OUT.mcap` and stopped with SIGINT leaves
an MCAP file that a reader this project did not write (the `mcap` package with
`mcap-ros2-support`'s decoder) opens, holding as many results as the robot's summary counts, the
cloud's answers among them; and a robot fed a rosbag2 bag (`bag:PATH`) serves every record with
its header stamp and ends the run by itself at the end of the bag, its recording whole.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from tests.e2e.conftest import TEST_INPUT_SHAPE
from tests.unit.bag_support import camera_records, photo_frames, write_bag

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
PREFIX = "/elasticfog/robot_1"
WAIT_S = 30.0
"""Bound of each wait for something the runtime does in well under a second or two."""
FRAMES_BEFORE_STOP = 12
BAG_FRAMES = 10
NS_PER_S = 1_000_000_000


def summary_of(log: str) -> dict[str, Any]:
    """The robot's `--json` summary: the last line of its output that is a JSON object."""
    lines = [line for line in log.splitlines() if line.startswith('{"robot"')]
    assert lines, f"no JSON summary in the robot's output:\n{log[-2000:]}"
    return dict(json.loads(lines[-1]))


def read_recording(path: Path) -> dict[str, list[Any]]:
    """Every decoded message of an MCAP file, by topic, in file order."""
    by_topic: dict[str, list[Any]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(decoded)
    return by_topic


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def test_a_recording_stopped_by_sigint_holds_as_many_results_as_the_summary(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    lf = local_fleet(make_fleet())
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    tap = lf.tap(ROBOT)
    out = tmp_path / "run.mcap"
    robot = lf.start_robot(
        ROBOT, "--policy", "cloud", "--source", "photo", "--record", str(out), "--json"
    )
    tap.wait_for(
        lambda r: r.get("deployment") == "edge-1" and not r.get("fallback"),
        timeout_s=WAIT_S,
        what="a frame answered by edge-1",
        procs=[robot],
    )
    tap.wait_frame(FRAMES_BEFORE_STOP, timeout_s=WAIT_S, procs=[robot])
    result = robot.stop()
    assert not result.killed and result.returncode == 0, robot.log_tail()

    summary = summary_of(robot.log_text())
    assert summary["answered"] > 0 and summary["stale_dropped"] == 0
    recorded = read_recording(out)
    assert f"{PREFIX}/input/compressed" in recorded, sorted(recorded)
    assert len(recorded) >= 2  # the input and at least one output
    for topic, messages in recorded.items():
        assert len(messages) == summary["frames"], (topic, len(messages), summary)
    frames = recorded[f"{PREFIX}/input/compressed"]
    assert {(f.format, bytes(f.data[:2])) for f in frames} == {("jpeg", b"\xff\xd8")}


def test_a_bag_is_served_whole_and_ends_the_run_with_its_recording(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    side = TEST_INPUT_SHAPE[1]
    records = camera_records(photo_frames(BAG_FRAMES, side, side), period_ns=30_000_000)
    bag = write_bag(tmp_path / "camera_bag", records, "sqlite3")
    lf = local_fleet(make_fleet())
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    out = tmp_path / "replay.mcap"
    robot = lf.start_robot(
        ROBOT, "--policy", "cloud", "--source", f"bag:{bag}", "--record", str(out), "--json"
    )
    assert robot.wait(WAIT_S) == 0, robot.log_tail()

    summary = summary_of(robot.log_text())
    assert summary["frames"] == BAG_FRAMES
    recorded = read_recording(out)
    frames = recorded[f"{PREFIX}/input/compressed"]
    assert len(frames) == BAG_FRAMES
    # Each frame's capture stamp is its bag record's header stamp (3 ms before the record time).
    assert [stamp_ns(f.header) for f in frames] == [r.time_ns - 3_000_000 for r in records]
    assert all(len(m) == BAG_FRAMES for m in recorded.values())
