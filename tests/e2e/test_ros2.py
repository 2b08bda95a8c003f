"""elasticfog as a ROS 2 participant, end to end, against a ROS 2 peer this project did not write.

zenoh-ros2-sdk (a pure-Python rmw_zenoh) publishes camera frames, a real photograph as
`sensor_msgs/msg/Image` rgb8 and as a JPEG `CompressedImage`, to a robot daemon subprocess (with
a registry and a cloud), and subscribes to the robot's `std_msgs/msg/Float32MultiArray` results:
they equal onnxruntime's output of the whole model on the same decoded image, and each carries
its frame's header stamp (the rmw_zenoh attachment's source timestamp, read with the SDK's own
attachment decoder). The SDK's graph discovery (what `ros2 topic list` does) sees the robot's
subscription and publishers. Bad input on the topic (truncated CDR, a wrong type hash, an unknown
encoding, a 0×0 image) is a named line in the robot's log, and the robot keeps serving. And
`elasticfog nav assist` filters an SDK teleop's Twists with the d_coll a stereo robot publishes.

The SDK's peer and the `.msg` files it reads are `tests.e2e.ros2_sdk`'s (its fixtures are the
tier's, in conftest).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from common import rmw_zenoh
from common.image_input import ImageInputs
from common.partition import load_partition
from common.partition.runtime import SplitModel
from deploy.readiness import wait_until
from robotd.sources.frame_sources import fit_frame
from tests.e2e.conftest import TEST_INPUT_SHAPE, TEST_MODEL
from tests.e2e.ros2_sdk import SdkPeer, header

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
CAMERA = "/camera/image_raw"
CAMERA_COMPRESSED = "/camera/image_raw/compressed"
RESULTS = "/elasticfog/robot_1"
WAIT_S = 30.0
# Raw tensors cross the network: a result equals the whole model's up to float rounding.
RESULT_ATOL = 1e-4


def photograph(height: int = 480, width: int = 640) -> np.ndarray:
    """A real photograph (scikit-image's astronaut) as RGB uint8 at the given size."""
    from skimage import data

    return np.ascontiguousarray(cv2.resize(data.astronaut(), (width, height)))


def reference(bgr: np.ndarray) -> dict[str, np.ndarray]:
    """onnxruntime's output of the whole model (its ONNX file) on a decoded BGR frame."""
    import onnxruntime as ort

    partition = load_partition(TEST_MODEL, input_shape=tuple(TEST_INPUT_SHAPE))
    inputs = ImageInputs(SplitModel(partition).input_specs())
    session = ort.InferenceSession(str(partition.full), providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    # The source fits a frame to the model's input as the photo source does
    # (robotd.sources.frame_sources).
    fitted = fit_frame(bgr, inputs.height, inputs.width)
    return dict(zip(names, session.run(names, inputs.feeds(fitted)), strict=True))


def start_fleet(make_fleet: Any, local_fleet: Any, source: str) -> tuple[Any, Any, int]:
    fleet = make_fleet(
        machines={ROBOT: {"source": source, "results": {"ros2": RESULTS}}},
    )
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    port = int(lf.registry_host_port[1])
    return fleet, lf, port


class Results:
    """Float32MultiArray results from the SDK subscriber, and their attachments' stamps from a
    plain Zenoh subscriber on the same key, decoded by the SDK's attachment reader."""

    def __init__(self, peer: SdkPeer, lf: Any, output: str) -> None:
        from zenoh_ros2_sdk.attachment import Attachment

        self.arrays: list[np.ndarray] = []
        self.stamps: list[int] = []
        self._cond = threading.Condition()
        topic = f"{RESULTS}/{rmw_zenoh.name_token(output)}"

        def on_array(msg: Any) -> None:
            dims = [int(d.size) for d in msg.layout.dim]
            with self._cond:
                self.arrays.append(np.asarray(msg.data, dtype=np.float32).reshape(dims))
                self._cond.notify_all()

        def on_sample(sample: Any) -> None:
            with self._cond:
                self.stamps.append(Attachment.from_bytes(sample.attachment.to_bytes()).timestamp_ns)
                self._cond.notify_all()

        peer.subscriber(topic, "std_msgs/msg/Float32MultiArray", on_array)
        array_type = rmw_zenoh.TopicType.of("std_msgs/msg/Float32MultiArray")
        self._raw = lf.session.declare_subscriber(
            rmw_zenoh.topic_key(0, topic, array_type), on_sample
        )

    def wait(self, count: int, what: str, procs: Any) -> None:
        wait_until(
            lambda: len(self.arrays) >= count and len(self.stamps) >= count,
            timeout_s=WAIT_S,
            what=what,
            procs=procs,
        )


def _topics(port: int) -> dict[str, list[str]]:
    from zenoh_ros2_sdk import get_topic_names_and_types

    return dict(get_topic_names_and_types(domain_id=0, router_port=port, timeout=1.0))


def _publish_and_check(
    publish: Any, frames: list[tuple[int, np.ndarray]], results: Results, robot: Any
) -> None:
    """Publish each frame once its predecessor's result came (one frame at a time: the robot
    keeps only the newest), and compare each result with the whole model on the frame."""
    for i, (stamp_ns, bgr) in enumerate(frames, start=len(results.arrays)):
        # Publish until the robot's subscription is matched and the first result comes (a
        # message sent before the robot's subscriber reached the router is not delivered).
        deadline = time.monotonic() + WAIT_S
        while len(results.arrays) <= i:  # bounded by the deadline
            publish(stamp_ns)
            with results._cond:
                results._cond.wait_for(lambda i=i: len(results.arrays) > i, timeout=1.0)
            assert time.monotonic() < deadline, f"no result for frame {i}\n{robot.log_tail()}"
        results.wait(i + 1, f"the attachment of result {i}", [robot])
        expected = next(iter(reference(bgr).values()))
        got = results.arrays[-1]
        assert got.shape == expected.shape
        assert np.allclose(got, expected, atol=RESULT_ATOL), float(np.abs(got - expected).max())
        assert results.stamps[-1] == stamp_ns, "the result's source timestamp is the frame's stamp"


def test_image_frames_in_float32_results_out(make_fleet, local_fleet, sdk_peer) -> None:
    _, lf, port = start_fleet(make_fleet, local_fleet, f"ros2:{CAMERA}")
    peer = sdk_peer(port)
    output = next(iter(reference(np.zeros((8, 8, 3), np.uint8))))
    results = Results(peer, lf, output)
    robot = lf.start_robot(ROBOT, "--policy", "cloud")
    camera = peer.publisher(CAMERA, "sensor_msgs/msg/Image")
    rgb = photograph()
    frames = [
        (1_700_000_000_000_000_000 + k * 33_000_000, np.roll(rgb, 40 * k, axis=1)) for k in range(3)
    ]

    def publish_for(stamp_ns: int) -> None:
        image = dict(frames)[stamp_ns]
        camera.publish(
            header=header(peer, stamp_ns),
            height=image.shape[0],
            width=image.shape[1],
            encoding="rgb8",
            is_bigendian=0,
            step=image.shape[1] * 3,
            data=image.reshape(-1),
        )

    _publish_and_check(
        publish_for, [(s, cv2.cvtColor(f, cv2.COLOR_RGB2BGR)) for s, f in frames], results, robot
    )
    topics = _topics(port)
    assert topics.get(CAMERA) and "sensor_msgs/msg/Image" in topics[CAMERA]
    results_topic = f"{RESULTS}/{rmw_zenoh.name_token(output)}"
    assert "std_msgs/msg/Float32MultiArray" in topics.get(results_topic, [])
    # `ros2 topic info -v`'s view: the robot's node subscribes to the camera, publishes results.
    from zenoh_ros2_sdk import get_topic_info

    camera_info = get_topic_info(CAMERA, domain_id=0, router_port=port, timeout=1.0, verbose=True)
    results_info = get_topic_info(
        results_topic, domain_id=0, router_port=port, timeout=1.0, verbose=True
    )
    assert camera_info is not None and results_info is not None
    node = rmw_zenoh.node_name_for(ROBOT)
    assert [(e.node_name, e.node_namespace) for e in camera_info.subscribers] == [(node, "/")]
    assert [(e.node_name, e.node_namespace) for e in results_info.publishers] == [(node, "/")]
    robot.check_alive()


def test_compressed_frames_in(make_fleet, local_fleet, sdk_peer) -> None:
    _, lf, port = start_fleet(make_fleet, local_fleet, f"ros2:{CAMERA_COMPRESSED},type=compressed")
    peer = sdk_peer(port)
    output = next(iter(reference(np.zeros((8, 8, 3), np.uint8))))
    results = Results(peer, lf, output)
    robot = lf.start_robot(ROBOT, "--policy", "cloud")
    camera = peer.publisher(CAMERA_COMPRESSED, "sensor_msgs/msg/CompressedImage")
    bgr = cv2.cvtColor(photograph(), cv2.COLOR_RGB2BGR)
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    decoded = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)  # what the robot sees: the decoded JPEG
    stamp = 1_700_000_123_000_000_007

    def publish(stamp_ns: int) -> None:
        camera.publish(header=header(peer, stamp_ns), format="jpeg", data=jpeg.reshape(-1))

    _publish_and_check(publish, [(stamp, decoded)], results, robot)
    robot.check_alive()


def test_bad_input_is_named_and_the_robot_keeps_serving(make_fleet, local_fleet, sdk_peer) -> None:
    """Truncated CDR, a wrong type hash on the topic, an unknown encoding and a 0×0 image: each is
    one named line in the robot's log, and the next good frame is served."""
    from common.ros2_messages import typestore

    _, lf, port = start_fleet(make_fleet, local_fleet, f"ros2:{CAMERA}")
    peer = sdk_peer(port)
    output = next(iter(reference(np.zeros((8, 8, 3), np.uint8))))
    results = Results(peer, lf, output)
    robot = lf.start_robot(ROBOT, "--policy", "cloud")
    camera = peer.publisher(CAMERA, "sensor_msgs/msg/Image")
    rgb = photograph(48, 64)
    image_type = rmw_zenoh.TopicType.of("sensor_msgs/msg/Image")
    key = rmw_zenoh.topic_key(0, CAMERA, image_type)

    def image(encoding: str, height: int, width: int, data: np.ndarray) -> dict[str, Any]:
        return dict(
            header=header(peer, 1_700_000_000_000_000_000),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=width * 3,
            data=data,
        )

    def good(stamp_ns: int) -> None:
        camera.publish(
            **{**image("rgb8", 48, 64, rgb.reshape(-1)), "header": header(peer, stamp_ns)}
        )

    _publish_and_check(good, [(1, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))], results, robot)
    msg_type = typestore().types["sensor_msgs/msg/Image"]
    valid = bytes(
        typestore().serialize_cdr(
            msg_type(**image("rgb8", 48, 64, rgb.reshape(-1))), "sensor_msgs/msg/Image"
        )
    )
    bad = {
        "MalformedMessage": (key, valid[: len(valid) // 2]),
        "WrongTypeHash": (key.rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64, valid),
        "UnknownEncoding": (key, None),
        "EmptyImage": (key, None),
    }
    for name, (where, payload) in bad.items():
        if name == "UnknownEncoding":
            camera.publish(**image("yuv422", 48, 64, rgb.reshape(-1)))
        elif name == "EmptyImage":
            camera.publish(**image("rgb8", 0, 0, np.zeros(0, np.uint8)))
        else:
            lf.session.put(where, payload)
        wait_until(
            lambda name=name: f"message refused: {name}" in robot.log_text() or None,
            timeout_s=WAIT_S,
            what=f"the robot's line naming {name}",
            procs=[robot],
        )
    served = len(results.arrays)
    _publish_and_check(good, [(2, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))], results, robot)
    assert len(results.arrays) > served
    lines = [line for line in robot.log_text().splitlines() if "message refused" in line]
    assert len(lines) == len(bad) and all("Traceback" not in line for line in lines), lines
    robot.check_alive()


def test_results_topic_over_the_input_is_a_config_error(make_fleet, tmp_path: Path) -> None:
    import subprocess

    from deploy.procs import elasticfog_argv

    fleet = make_fleet()
    done = subprocess.run(
        [
            *elasticfog_argv(),
            "robot",
            "--config",
            str(fleet.config),
            "--id",
            ROBOT,
            "--source",
            "ros2:/elasticfog/robot_1/camera",
            "--results-ros2",
            RESULTS,
        ],
        capture_output=True,
        text=True,
        timeout=WAIT_S,
        check=False,
    )
    assert done.returncode == 2, done.stderr
    assert "collides with the input topic /elasticfog/robot_1/camera" in done.stderr
    assert "Traceback" not in done.stderr


STEREO_MODEL = "zoo:stereo"
STEREO_SHAPE = [3, 120, 160]


def _wait_tokens(session: Any, patterns: list[str], procs: Any) -> None:
    """Until a liveliness token matching each pattern is alive."""
    import zenoh

    seen: set[str] = set()

    def on_token(sample: Any) -> None:
        key = zenoh.KeyExpr(str(sample.key_expr))
        seen.update(p for p in patterns if zenoh.KeyExpr(p).intersects(key))

    sub = session.liveliness().declare_subscriber("@ros2_lv/**", on_token, history=True)
    try:
        wait_until(
            lambda: len(seen) == len(patterns) or None,
            timeout_s=WAIT_S,
            what=f"tokens {patterns}",
            procs=procs,
        )
    finally:
        sub.undeclare()


def test_nav_assist_filters_teleop_with_the_fleets_d_coll(
    make_fleet, local_fleet, sdk_peer
) -> None:
    """A stereo robot (zoo:stereo on stereo:world) publishes d_coll on ROS 2; `elasticfog nav
    assist` turns a zenoh-ros2-sdk teleop's Twists into safe ones that a zenoh-ros2-sdk base
    receives: no forward motion until the first d_coll, then forward motion allowed, never faster
    than asked."""
    from common.partition import load_partition

    load_partition(STEREO_MODEL, input_shape=tuple(STEREO_SHAPE))
    fleet = make_fleet(
        model=STEREO_MODEL,
        input_shape=STEREO_SHAPE,
        machines={ROBOT: {"source": "stereo:world", "results": {"ros2": RESULTS}}},
    )
    lf = local_fleet(fleet)
    lf.start_registry()  # no cloud: the robot computes d_coll itself (--policy robot)
    port = int(lf.registry_host_port[1])
    peer = sdk_peer(port)
    safe: list[tuple[float, float]] = []
    cond = threading.Condition()

    def on_safe(msg: Any) -> None:
        with cond:
            safe.append((float(msg.linear.x), float(msg.angular.z)))
            cond.notify_all()

    peer.subscriber("/cmd_vel", "geometry_msgs/msg/Twist", on_safe)
    assist = lf.procs.start(
        "assist",
        ["nav", "assist", "--config", str(fleet.config), "--robot", ROBOT],
    )
    _wait_tokens(
        lf.session,
        ["@ros2_lv/0/*/*/*/MS/%/%/elasticfog_assist_robot_1/%cmd_vel_teleop/**"],
        [assist],
    )
    teleop = peer.publisher("/cmd_vel_teleop", "geometry_msgs/msg/Twist")
    vector = peer.types("geometry_msgs/msg/Vector3")

    def drive(count: int) -> list[tuple[float, float]]:
        start = len(safe)
        deadline = time.monotonic() + WAIT_S
        while len(safe) < start + count:  # bounded by the deadline
            teleop.publish(linear=vector(x=0.3, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.1))
            with cond:
                cond.wait_for(lambda: len(safe) > start, timeout=0.2)
            assert time.monotonic() < deadline, f"no safe command\n{assist.log_tail()}"
        return safe[start:]

    # No robot yet, so no d_coll: the assistant lets nothing move forward.
    assert all(v == 0.0 for v, _ in drive(3))
    robot = lf.start_robot(ROBOT, "--policy", "robot")
    deadline = time.monotonic() + WAIT_S * 2
    moving: list[tuple[float, float]] = []
    while not moving:  # bounded by the deadline
        moving = [c for c in drive(1) if c[0] > 0.0]
        assert time.monotonic() < deadline, f"never allowed to move\n{robot.log_tail()}"
    v, w = moving[0]
    assert 0.0 < v <= 0.3 and w == pytest.approx(0.1 * v / 0.3), "same path, never faster"
    robot.check_alive()
    assist.check_alive()
