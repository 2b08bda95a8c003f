"""The robot daemon on recordings, over a real Zenoh session on loopback: a rosbag2 bag (both
storages) and a video file play at their own recorded pace unless `--fps` is given, each frame
carries its recorded capture stamp into its result, and the end of the recording ends the run
with every frame in the summary (bad records refused, the others served).

Regression guarded: a 60-frame 15 fps video ran 1,184 frames at the config's 10 fps until killed.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from common.cli import app
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from tests.integration.conftest import Router
from tests.integration.test_robotd import DEPLOYMENT, ROBOT, fleet_config, tiny_conv_model
from tests.integration.test_robotd_cli import write_fleet
from tests.unit.bag_support import STORAGES, Record, camera_records, photo_frames, write_bag
from tests.unit.test_partition import save

BAG_FRAMES = 8
BAG_PERIOD_NS = 60_000_000
LAG_NS = 2_000_000
VIDEO_FRAMES = 12
VIDEO_FPS = 30.0
# The config's rate in the video test: far slower than the file's, so the two cannot be confused.
CONFIG_FPS = 2.0
# Slower than the bag's 16.7 records/s: --fps wins over the recorded pace.
GIVEN_FPS = 5.0
# A paced run may start its frames a little early on a loaded host (timer granularity): none
# starts earlier than this share of its recorded offset.
PACE_SLACK = 0.9
# How long the robot waits for a registry and a route at start: none runs here (policy robot).
WAIT_S = 0.2


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(tiny_conv_model(), tmp_path_factory.mktemp("model") / "tiny.onnx")


def run_robot(
    endpoint: str,
    model_file: Path,
    source: str,
    *,
    fps: float | None = None,
    robot_fps: float | None = None,
) -> tuple[RobotDaemon, list[FrameResult]]:
    """Run the robot (policy robot: no deployment needed) until its source ends; `fps` is the
    --fps option, `robot_fps` the machine's fps in the fleet file."""
    robot: dict[str, object] = {"role": "robot", "listen": ["tcp/127.0.0.1:0"]}
    if robot_fps is not None:
        robot["fps"] = robot_fps
    machines = {DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]}, ROBOT: robot}
    cfg = fleet_config(endpoint, model_file, policy={"kind": "robot"}, machines=machines)
    options = RobotOptions(source=source, fps=fps, registry_wait_s=WAIT_S, route_wait_s=WAIT_S)
    results: list[FrameResult] = []
    daemon = RobotDaemon(cfg, ROBOT, options, on_result=results.append)
    assert daemon.run() == 0
    return daemon, results


def elapsed_s(daemon: RobotDaemon) -> float:
    summary = daemon.summary
    assert summary.started_at is not None and summary.ended_at is not None
    return summary.ended_at - summary.started_at


@pytest.mark.parametrize("storage", STORAGES)
def test_a_bag_plays_at_its_recorded_pace_and_its_end_ends_the_run(
    zenoh_router: Router, model_file: Path, tmp_path: Path, storage: str
) -> None:
    records = camera_records(
        photo_frames(BAG_FRAMES, 32, 40), period_ns=BAG_PERIOD_NS, stamp_lag_ns=LAG_NS
    )
    bag = write_bag(tmp_path / "run", records, storage)
    daemon, results = run_robot(zenoh_router.endpoint, model_file, f"bag:{bag}")
    assert daemon.summary.frames == BAG_FRAMES
    assert [r.frame for r in results] == list(range(BAG_FRAMES))
    assert [r.stamp_ns for r in results] == [r.time_ns - LAG_NS for r in records]
    recorded_s = (BAG_FRAMES - 1) * BAG_PERIOD_NS / 1e9
    assert elapsed_s(daemon) >= PACE_SLACK * recorded_s


def test_fps_given_wins_over_the_recorded_pace(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    records = camera_records(photo_frames(4, 32, 40), period_ns=BAG_PERIOD_NS)
    bag = write_bag(tmp_path / "run", records)
    daemon, results = run_robot(zenoh_router.endpoint, model_file, f"bag:{bag}", fps=GIVEN_FPS)
    assert len(results) == 4
    assert elapsed_s(daemon) >= PACE_SLACK * 3 / GIVEN_FPS  # not the recorded 0.18 s


def test_a_bag_with_bad_records_serves_every_good_one(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    records = camera_records(
        photo_frames(5, 32, 40), compressed=True, period_ns=1_000_000, stamp_lag_ns=LAG_NS
    )
    cut = records[2]
    records[2] = Record(cut.topic, cut.msgtype, cut.time_ns, cut.payload[: len(cut.payload) // 3])
    bag = write_bag(tmp_path / "run", records, "sqlite3")
    daemon, results = run_robot(zenoh_router.endpoint, model_file, f"bag:{bag}")
    assert daemon.summary.frames == 4
    assert daemon.summary.rejected_frames == {"malformed": 1}
    kept = [r for i, r in enumerate(records) if i != 2]
    assert [r.stamp_ns for r in results] == [r.time_ns - LAG_NS for r in kept]


def test_a_video_without_loop_plays_at_its_own_rate_and_ends_the_run(
    zenoh_router: Router, model_file: Path, tmp_path: Path
) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), VIDEO_FPS, (40, 32))
    assert writer.isOpened()
    for frame in photo_frames(VIDEO_FRAMES, 32, 40):
        writer.write(frame)
    writer.release()
    daemon, results = run_robot(
        zenoh_router.endpoint, model_file, f"video:{path},loop=false", robot_fps=CONFIG_FPS
    )
    assert daemon.summary.frames == VIDEO_FRAMES == len(results)
    took = elapsed_s(daemon)
    assert took >= PACE_SLACK * (VIDEO_FRAMES - 1) / VIDEO_FPS
    # At the config's 2 fps the 12 frames would take 5.5 s.
    assert took < (VIDEO_FRAMES - 1) / CONFIG_FPS / 2
    assert all(np.isfinite(r.outputs["logits"]).all() for r in results)


@pytest.mark.parametrize(
    ("topic", "message"),
    [
        ("", "2 image topics (/front, /rear); name one: bag:{bag}:TOPIC"),
        (":/side", "has no topic /side; its topics: /front (sensor_msgs/msg/Image), /rear"),
    ],
)
def test_a_bag_topic_error_is_one_line_as_written_and_exit_code_2(
    zenoh_router: Router,
    model_file: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    topic: str,
    message: str,
) -> None:
    """Regression: the CLI's error line took `:two:` in `bag:two:TOPIC` for an emoji code."""
    frames = photo_frames(2, 32, 40)
    records = camera_records(frames, topic="/front") + camera_records(frames, topic="/rear")
    bag = write_bag(tmp_path / "two", records).name
    fleet = write_fleet(tmp_path, zenoh_router.endpoint, model_file)
    monkeypatch.chdir(tmp_path)
    args = ["robot", "--config", str(fleet), "--id", ROBOT, "--source", f"bag:{bag}{topic}"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message.format(bag=bag) in errors[0], result.stderr
