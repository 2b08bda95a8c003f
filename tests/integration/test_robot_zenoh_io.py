"""Frames in and results out over real Zenoh on loopback: a robot daemon (in a thread) with
`source: zenoh`, fed and read by the application client (`robotd.results.client.RobotClient`, a
Zenoh client of the router, as an application on another host would be).

What must hold: each result carries the stamp its frame was sent with, and outputs equal to the
whole model run on the decoded, fitted image; the robot works on the newest frame, and every
frame sent is either served or counted as dropped (`dropped_stale`), none lost; a frame that
cannot be decoded is counted by its error code and the robot keeps serving.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from common import keys
from common.config import FleetConfig
from common.image_input import ImageInputs
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.wire import encode_raw
from common.wire.app_to_robot import FrameIn, ImageEncoding, ImageIn, decode_image, image_in
from common.wire.robot_to_app import ServedBy
from deploy import readiness
from robotd.daemon import RobotDaemon, RobotOptions
from robotd.results.client import RobotClient
from robotd.sources.frame_sources import MAX_SOURCE_SIDE_PX, fit_frame
from tests.helpers.onnx_graphs import save
from tests.integration.conftest import Router
from tests.integration.test_robotd import (
    FLEET,
    ROBOT,
    FakeDeployment,
    fleet_config,
    tiny_conv_model,
)

WAIT_S = 10.0
TOLERANCE = 1e-4
FRAMES = 4
BURST = 30
POLL_S = 0.01
SMALL_LIMIT_BYTES = 1 << 20


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(tiny_conv_model(), tmp_path_factory.mktemp("model") / "tiny.onnx")


@pytest.fixture
def fake_registry(zenoh_peer: zenoh.Session) -> Iterator[zenoh.Session]:
    """The registry's token only: the robot does not report the registry missing."""
    token = zenoh_peer.liveliness().declare_token(keys.alive_registry(FLEET, "registry"))
    yield zenoh_peer
    token.undeclare()


def photograph(height: int = 120, width: int = 160, shift: int = 0) -> np.ndarray:
    """A real photograph (scikit-image's, as the photo source shows them), cropped."""
    from common.photos import photo_bgr

    image = photo_bgr("astronaut")
    return np.ascontiguousarray(
        image[shift : shift + height * 3 : 3, shift : shift + width * 3 : 3]
    )


def wait_until(condition: Callable[[], bool], timeout_s: float = WAIT_S) -> bool:
    """Whether `condition()` held within `timeout_s` (looked at every POLL_S)."""
    return bool(readiness.wait_until(condition, timeout_s=timeout_s, what="the condition"))


class RunningRobot:
    """The daemon's `run()` in a thread; stopped and joined by `stop()`."""

    def __init__(self, cfg: FleetConfig, **options: object) -> None:
        options.setdefault("registry_wait_s", WAIT_S)
        options.setdefault("route_wait_s", 0.1)
        options.setdefault("policy", "robot")
        self.daemon = RobotDaemon(cfg, ROBOT, RobotOptions(source="zenoh", **options))  # type: ignore[arg-type]
        self.code: int | None = None
        self.thread = threading.Thread(target=self._run, name="robot", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.code = self.daemon.run()

    def stop(self) -> None:
        self.daemon.stop()
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "the robot did not stop"
        assert self.code == 0


@pytest.fixture
def robot_and_client(
    zenoh_router: Router, model_file: Path, fake_registry: zenoh.Session
) -> Iterator[tuple[RunningRobot, RobotClient]]:
    cfg = fleet_config(zenoh_router.endpoint, model_file)
    robot = RunningRobot(cfg, metrics_port=0)  # any free port: its counts are read here too
    client = RobotClient(cfg, ROBOT)
    try:
        assert client.wait_for_robot(WAIT_S), "the robot's zenoh source never subscribed"
        yield robot, client
    finally:
        client.close()
        robot.stop()


def source_counts(daemon: RobotDaemon) -> tuple[float | None, float | None]:
    """(dropped_stale, rejected frames) as the robot's /metrics registry has them."""
    assert daemon.metrics is not None, "the robot serves no metrics"
    registry, labels = daemon.metrics.registry, {"robot": ROBOT}
    return (
        registry.get_sample_value("elasticfog_robot_dropped_stale_frames_total", labels),
        registry.get_sample_value("elasticfog_robot_rejected_frames_total", labels),
    )


def reference(model: SplitModel, image: ImageIn) -> dict[str, np.ndarray]:
    """The whole model on the image as the robot decodes and fits it."""
    inputs = ImageInputs(model.input_specs())
    fit = (inputs.height, inputs.width)
    bgr = decode_image(image, max_side_px=MAX_SOURCE_SIDE_PX, fit=fit)
    return model.run_full(inputs.feeds(fit_frame(bgr, inputs.height, inputs.width)))


@pytest.mark.parametrize("encoding", ["jpeg", "png", "rgb8", "mono8"])
def test_each_result_carries_its_stamp_and_the_whole_models_outputs(
    robot_and_client: tuple[RunningRobot, RobotClient], model_file: Path, encoding: str
) -> None:
    _, client = robot_and_client
    model = SplitModel(load_partition(str(model_file)))
    for n in range(FRAMES):
        image = image_in(photograph(shift=n), encoding)
        stamp = 1_700_000_000_000_000_000 + n
        sent = client.send(FrameIn(stamp_ns=stamp, images={"image": image}))
        assert sent == stamp
        result = next(client.results(timeout=WAIT_S))
        assert result.stamp_ns == stamp and result.frame == n
        assert result.served_by is ServedBy.ROBOT and result.message.action == "P"
        assert result.message.robot == ROBOT and result.latency_s > 0
        assert result.message.published_ns >= result.message.stamp_ns
        want = reference(model, image)
        assert result.outputs.keys() == want.keys()
        for name, value in want.items():
            np.testing.assert_allclose(result.outputs[name], value, atol=TOLERANCE)


def test_infer_waits_for_its_own_frame(robot_and_client: tuple[RunningRobot, RobotClient]) -> None:
    _, client = robot_and_client
    first = client.infer(photograph(), timeout=WAIT_S)
    second = client.infer(photograph(shift=2), timeout=WAIT_S)
    assert second.stamp_ns > first.stamp_ns and second.frame == first.frame + 1


def test_the_robot_takes_the_newest_frame_and_counts_every_dropped_one(
    zenoh_router: Router, model_file: Path, fake_registry: zenoh.Session
) -> None:
    """A burst faster than the robot serves (each frame stretched by --robot-slowdown): every
    frame sent is served or counted as dropped; results come in stamp order."""
    cfg = fleet_config(zenoh_router.endpoint, model_file)
    robot = RunningRobot(cfg, robot_slowdown=200.0, metrics_port=0)
    try:
        with RobotClient(cfg, ROBOT, encoding=ImageEncoding.BGR8) as client:
            assert client.wait_for_robot(WAIT_S)
            stamps = [client.send(photograph(shift=i % 5)) for i in range(BURST)]
            results = []
            for result in client.results(timeout=WAIT_S):
                results.append(result)
                if result.stamp_ns == stamps[-1]:
                    break
    finally:
        robot.stop()
    got = [r.stamp_ns for r in results]
    assert got and got[-1] == stamps[-1], "the newest frame was not served"
    assert got == sorted(got) and set(got) <= set(stamps)
    summary = robot.daemon.summary.to_json()
    assert summary["frames"] == len(results)
    assert summary["dropped_stale"] > 0
    assert summary["frames"] + summary["dropped_stale"] == BURST
    assert summary["rejected_frames"] == {}
    # The metrics count what the summary counts.
    assert source_counts(robot.daemon) == (summary["dropped_stale"], 0)


def test_a_frame_that_cannot_be_decoded_is_counted_and_the_robot_keeps_serving(
    robot_and_client: tuple[RunningRobot, RobotClient],
) -> None:
    robot, client = robot_and_client
    jpeg = image_in(photograph(), "jpeg")
    truncated = FrameIn(
        stamp_ns=5,
        images={"image": ImageIn(encoding=ImageEncoding.JPEG, data=bytes(jpeg.data)[:64])},
    )
    two_images = FrameIn(stamp_ns=6, images={"a": jpeg, "b": jpeg})
    bad = (b"\xc1 not msgpack", encode_raw({"v": 99}), truncated.to_wire(), two_images.to_wire())
    assert robot.daemon.ready.wait(WAIT_S), "the robot did not start"
    source = robot.daemon.loop.source
    for n, payload in enumerate(bad, start=1):
        # The client's session already reaches the robot's subscriber.
        client.session.put(keys.frames_in(FLEET, ROBOT), payload)
        # One at a time (the robot keeps only the newest frame waiting): until it is rejected.
        assert wait_until(lambda n=n: sum(source.rejected_frames().values()) == n)
        result = client.infer(photograph(), timeout=WAIT_S)
        assert result.served_by is ServedBy.ROBOT
    robot.stop()
    assert robot.daemon.summary.dropped_stale == 0
    assert robot.daemon.summary.rejected_frames == {
        "malformed": 1,
        "schema_version": 1,
        "corrupt_payload": 1,
        "bad_value": 1,
    }
    assert source_counts(robot.daemon) == (0, 4)  # the four refused above


def test_a_pipelined_frames_result_comes_without_waiting_for_the_next_frame(
    zenoh_router: Router,
    model_file: Path,
    fake_registry: zenoh.Session,
    open_peer: Callable[..., zenoh.Session],
) -> None:
    """Regression guard: with frames in flight (max_in_flight > 1) the loop waits for the
    sender's next frame; the result of the frame in flight must still come when it settles."""
    split = SplitModel(load_partition(str(model_file)))
    dep = FakeDeployment(open_peer(), split)
    cfg = fleet_config(zenoh_router.endpoint, model_file)
    robot = RunningRobot(cfg, policy="cloud", max_in_flight=2, route_wait_s=WAIT_S)
    try:
        with RobotClient(cfg, ROBOT) as client:
            assert client.wait_for_robot(WAIT_S)
            for _ in range(3):
                result = client.infer(photograph(), timeout=WAIT_S)
                assert result.served_by is ServedBy.CLOUD
    finally:
        robot.stop()
        dep.close()


def test_a_frame_over_the_payload_limit_is_refused_before_it_is_copied(
    zenoh_router: Router, model_file: Path, fake_registry: zenoh.Session
) -> None:
    cfg = fleet_config(zenoh_router.endpoint, model_file, max_payload_bytes=SMALL_LIMIT_BYTES)
    robot = RunningRobot(cfg)
    try:
        with RobotClient(cfg, ROBOT, encoding=ImageEncoding.BGR8) as client:
            assert client.wait_for_robot(WAIT_S)
            client.send(np.zeros((600, 800, 3), np.uint8))  # 1.4 MB raw
            assert robot.daemon.ready.wait(WAIT_S), "the robot did not start"
            source = robot.daemon.loop.source
            assert wait_until(lambda: source.rejected_frames() == {"too_large": 1})
            small = image_in(photograph(), "jpeg")
            result = client.infer(decode_image(small, max_side_px=MAX_SOURCE_SIDE_PX), WAIT_S)
            assert result.served_by is ServedBy.ROBOT
    finally:
        robot.stop()
    assert robot.daemon.summary.rejected_frames == {"too_large": 1}
