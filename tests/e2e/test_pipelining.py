"""Pipelined frames end to end: registry, a cloud daemon and the robot as real subprocesses on
loopback, the robot's uplink paced in the application (`--uplink-mbit`), the cloud's processing
lengthened by its fault injection (a fixed delay before each reply, which holds no worker), and a
frame rate above what one frame at a time allows. The deployment's batching config is the
default one: the robot announces its frames in flight at registration and is admitted as many.

The same fleet runs the robot twice, one frame in flight and then three (`--max-in-flight`):
with three the frames per second delivered are higher, every frame has its telemetry record (0
lost), and the results applied (records not marked `stale`) come in increasing frame order.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from deploy.demo import answered_by, read_telemetry
from deploy.local_fleet import LocalFleet

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
FRAMES = 36
UPLINK_MBIT = 2.0
"""A 64x64 camera frame sent whole (12 KiB) takes about 50 ms on this link."""
CLOUD_DELAY_MS = 150.0
"""The cloud's processing of each frame: one frame at a time gets about 1 / 0.2 s = 5 frames/s."""
FPS = 15.0
"""Above what one frame at a time allows, under what three in flight and the link allow."""
IN_FLIGHT = 3
GAIN = 1.5
"""Three in flight must deliver at least this many times the frames per second of one (about
2.5x expected: the link and the cloud's delay overlap across frames)."""
RUN_S = 60.0


def _fleet_changes() -> dict[str, Any]:
    return {
        "machines": {
            # The default batching config: the robot announces its frames in flight at
            # registration, and the deployment admits as many (its default cap is above them).
            "edge-1": {"fault": {"delay_ms": CLOUD_DELAY_MS}},
            ROBOT: {"fps": FPS},
        }
    }


def _run_robot(lf: LocalFleet, tmp_path: Path, in_flight: int) -> tuple[list[dict], dict]:
    """One run of `FRAMES` frames: its telemetry records and its `--json` summary."""
    telemetry = tmp_path / f"in-flight-{in_flight}.jsonl"
    robot = lf.start_robot(
        ROBOT,
        *("--policy", "cloud", "--uplink-mbit", str(UPLINK_MBIT)),
        *("--max-in-flight", str(in_flight), "--json"),
        frames=FRAMES,
        telemetry=telemetry,
    )
    assert robot.wait(RUN_S) == 0, robot.log_tail()
    short = [ln for ln in robot.log_text().splitlines() if "admit(s) fewer" in ln]
    assert not any("edge-1 (" in ln for ln in short), f"edge-1 admits them all: {short}"
    lines = [ln for ln in robot.log_text().splitlines() if ln.startswith('{"robot"')]
    assert lines, f"no --json summary in the robot's output: {robot.log_tail()}"
    return read_telemetry(telemetry), json.loads(lines[-1])


def _delivered_fps(records: list[dict[str, Any]]) -> float:
    """Results applied per second, between the first and the last one applied."""
    applied = [r for r in records if not r["stale"]]
    span = applied[-1]["at"] - applied[0]["at"]
    assert span > 0, applied
    return (len(applied) - 1) / span


def test_three_frames_in_flight_deliver_more_frames_per_second(
    make_fleet, local_fleet, tmp_path: Path
) -> None:
    lf = local_fleet(make_fleet(**_fleet_changes()))
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    figures = {}
    for in_flight in (1, IN_FLIGHT):
        records, summary = _run_robot(lf, tmp_path, in_flight)
        frames = [int(r["frame"]) for r in records]
        assert sorted(frames) == list(range(FRAMES)), f"lost or repeated frames: {frames}"
        applied = [int(r["frame"]) for r in records if not r["stale"]]
        assert applied == sorted(set(applied)), f"a result applied out of order: {applied}"
        stale = sum(1 for r in records if r["stale"])
        assert summary["stale_dropped"] == stale and summary["frames"] == FRAMES, summary
        answered = sum(1 for r in records if answered_by(r) == "edge-1")
        assert answered >= 0.8 * FRAMES, (in_flight, summary)
        figures[in_flight] = (_delivered_fps(records), stale, summary)
    one, many = figures[1][0], figures[IN_FLIGHT][0]
    print(
        f"frames/s delivered: {one:.1f} with 1 in flight, {many:.1f} with {IN_FLIGHT} "
        f"({figures[IN_FLIGHT][1]} stale); summaries: {figures[1][2]} / {figures[IN_FLIGHT][2]}"
    )
    assert figures[1][1] == 0, "one frame in flight has nothing to overtake it"
    assert many >= GAIN * one, f"{many:.1f} frames/s with {IN_FLIGHT} in flight, {one:.1f} with 1"
