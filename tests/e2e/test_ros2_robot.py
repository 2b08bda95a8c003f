"""A real robot's ROS 2 setup end to end (issue 33): its ROS graph local, on a router of its own
(rmw_zenohd's stand-in: a plain Zenoh router in this process), its fleet over mutual TLS with
access control (`elasticfog init --tls`'s files), and zenoh-ros2-sdk, an rmw_zenoh this project
did not write, as the ROS 2 camera, planner and teleop on that router.

What must hold:
- the robot speaks ROS 2 through a session of its own (`ros2.endpoint`): every result's header
  (the TensorList's, the Classification's, the model view's CameraInfo's) equals its input
  image's, stamp and frame id; the TensorList and the Classification, decoded by the SDK with
  upstream's definitions (`tests.e2e.ros2_sdk`), equal onnxruntime's output of the whole model
  (the Classification: the softmax's top 5); the CameraInfo maps the model's view onto the
  camera's;
- nothing of the fleet is visible on the ROS 2 router: every liveliness token there is ROS 2's,
  no data key of the fleet (`ef/...`) passes it, and only the robot's ROS 2 session and the SDK
  are its peers;
- a stereo camera published on two topics with its CameraInfos drives `elasticfog nav assist`
  (also on the ROS 2 router): a near wall slows the operator's command, a far one passes it
  unchanged, and the robot reads the pair's geometry from the CameraInfos.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from common.config import load_fleet
from common.partition import load_partition
from common.session import open_session
from deploy.local_fleet import write_local_fleet
from deploy.procs import free_tcp_port
from deploy.readiness import wait_until
from tests.e2e.conftest import (
    TEST_DEADLINE_S,
    TEST_FPS,
    TEST_INPUT_SHAPE,
    TEST_MODEL,
    Fleet,
)
from tests.e2e.ros2_sdk import SdkPeer, header
from tests.e2e.test_ros2 import photograph, reference

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
CAMERA = "/camera/image_raw"
CAMERA_INFO = "/camera/camera_info"
RESULTS = "/elasticfog/robot_1"
WAIT_S = 30.0
RESULT_ATOL = 1e-4
T0 = 1_700_000_000_000_000_000
CAMERA_FX = 500.0


class Ros2Router:
    """The ROS 2 graph's own router (what rmw_zenohd is on a robot host), and what passed it."""

    def __init__(self) -> None:
        self.port = free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.session = open_session(router=True, listen=[self.endpoint])
        # A plain peer of that router: what any ROS 2 node there could see.
        self.observer = open_session(connect=[self.endpoint], listen=["tcp/127.0.0.1:0"])
        self.keys: set[str] = set()
        self._lock = threading.Lock()
        self._sub = self.observer.declare_subscriber("**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys.add(str(sample.key_expr))

    def tokens(self, key: str) -> list[str]:
        replies = self.observer.liveliness().get(key, timeout=2.0)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def close(self) -> None:
        self._sub.undeclare()
        self.observer.close()
        self.session.close()


@pytest.fixture
def ros2_router() -> Iterator[Ros2Router]:
    router = Ros2Router()
    try:
        yield router
    finally:
        router.close()


def _fleet(
    directory: Path, changes: dict[str, Any], *, tls: bool, model: str = TEST_MODEL
) -> Fleet:
    import uuid

    import yaml

    name = f"e2e-ros2-{uuid.uuid4().hex[:8]}"
    path = write_local_fleet(directory, fleet=name, model=model, changes=changes, tls=tls)
    return Fleet(dir=directory, config=path, name=name, data=yaml.safe_load(path.read_text()))


class Stamped:
    """Messages of one topic from the SDK subscriber, by their header's stamp."""

    def __init__(self, peer: SdkPeer, topic: str, msg_type: str) -> None:
        self.by_stamp: dict[int, Any] = {}
        self._cond = threading.Condition()
        peer.subscriber(topic, msg_type, self._on_msg)

    def _on_msg(self, msg: Any) -> None:
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        with self._cond:
            self.by_stamp[stamp] = msg
            self._cond.notify_all()

    def wait(self, stamp_ns: int, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: stamp_ns in self.by_stamp, timeout=timeout_s)


def _camera_info(peer: SdkPeer, height: int, width: int, p3: float = 0.0) -> dict[str, Any]:
    """A calibrated camera of `height`×`width` (its principal point the centre) as the SDK's
    CameraInfo fields."""
    fx, cx, cy = CAMERA_FX * width / 640, (width - 1) / 2, (height - 1) / 2
    roi = peer.types("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return dict(
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([fx, 0, cx, 0, fx, cy, 0, 0, 1], np.float64),
        r=np.eye(3).reshape(-1),
        p=np.array([fx, 0, cx, p3, 0, fx, cy, 0, 0, 0, 1, 0], np.float64),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def _same_header(msg: Any, stamp_ns: int, frame_id: str) -> bool:
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    got = msg.header
    return (int(got.stamp.sec), int(got.stamp.nanosec), str(got.frame_id)) == (
        sec,
        nanosec,
        frame_id,
    )


def test_beside_a_mutual_tls_fleet_results_carry_their_inputs_headers(
    tmp_path: Path, local_fleet: Any, sdk_peer: Any, e2e_cache: Path, ros2_router: Ros2Router
) -> None:
    fleet = _fleet(
        tmp_path / "fleet",
        {
            "input_shape": TEST_INPUT_SHAPE,
            "deadline_s": TEST_DEADLINE_S,
            "ros2": {"endpoint": ros2_router.endpoint},
            "machines": {
                ROBOT: {
                    "fps": TEST_FPS,
                    "source": f"ros2:{CAMERA}",
                    "results": {"ros2": RESULTS},
                }
            },
        },
        tls=True,
    )
    cfg = load_fleet(fleet.config)
    assert cfg.mtls and cfg.access_control
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    peer = sdk_peer(ros2_router.port)
    tensors = Stamped(peer, f"{RESULTS}/tensors", "isaac_ros_tensor_list_interfaces/msg/TensorList")
    classes = Stamped(peer, f"{RESULTS}/logits/classification", "vision_msgs/msg/Classification")
    views = Stamped(peer, f"{RESULTS}/camera_info", "sensor_msgs/msg/CameraInfo")
    robot = lf.start_robot(ROBOT, "--policy", "cloud")
    camera = peer.publisher(CAMERA, "sensor_msgs/msg/Image")
    camera_info = peer.publisher(CAMERA_INFO, "sensor_msgs/msg/CameraInfo")
    rgb = photograph()
    for k in range(3):
        stamp, frame_id = T0 + k * 33_000_000 + 7, f"camera_optical_{k}"
        image = np.ascontiguousarray(np.roll(rgb, 40 * k, axis=1))
        deadline = time.monotonic() + WAIT_S
        while not (
            tensors.wait(stamp, 0.5) and classes.wait(stamp, 0.5) and views.wait(stamp, 0.5)
        ):
            camera_info.publish(
                header=header(peer, stamp, frame_id), **_camera_info(peer, 480, 640)
            )
            camera.publish(
                header=header(peer, stamp, frame_id),
                height=480,
                width=640,
                encoding="rgb8",
                is_bigendian=0,
                step=640 * 3,
                data=image.reshape(-1),
            )
            assert time.monotonic() < deadline, f"no results for frame {k}\n{robot.log_tail()}"
        tensor_list, classification, view = (
            tensors.by_stamp[stamp],
            classes.by_stamp[stamp],
            views.by_stamp[stamp],
        )
        for msg in (tensor_list, classification, view):
            assert _same_header(msg, stamp, frame_id), msg.header
        expected = reference(image[..., ::-1].copy())["logits"]
        (tensor,) = tensor_list.tensors
        assert (tensor.name, int(tensor.data_type), int(tensor.shape.rank)) == ("logits", 9, 2)
        assert list(tensor.shape.dims) == [1, 1000] and list(tensor.strides) == [4000, 4]
        got = np.frombuffer(bytes(bytearray(tensor.data)), "<f4").reshape(1, 1000)
        assert np.allclose(got, expected, atol=RESULT_ATOL), float(np.abs(got - expected).max())
        probs = np.exp(expected[0] - expected.max()) / np.exp(expected[0] - expected.max()).sum()
        scores = [float(h.score) for h in classification.results]
        assert len(scores) == 5 and scores == pytest.approx(sorted(probs)[::-1][:5], abs=1e-5)
        for hypothesis in classification.results:
            assert float(hypothesis.score) == pytest.approx(
                probs[int(hypothesis.class_id)], abs=1e-5
            )
        # The model's 64×64 view: the centred 480×480 square, scaled by 64/480.
        assert (int(view.height), int(view.width)) == (64, 64)
        assert (int(view.roi.x_offset), int(view.roi.y_offset), int(view.roi.width)) == (80, 0, 480)
        if k > 0:  # the camera's CameraInfo has come by now (the first frame may precede it)
            assert float(view.k[0]) == pytest.approx(CAMERA_FX * 64 / 480)
            assert float(view.k[2]) == pytest.approx(31.5)
    # Nothing of the fleet on the ROS 2 router: ROS 2 tokens only, no fleet data, two peers.
    tokens = ros2_router.tokens("@ros2_lv/**")
    assert any("elasticfog_robot_1" in t for t in tokens), tokens
    assert ros2_router.tokens("ef/**") == [], "a fleet token on the ROS 2 router"
    assert any(k.startswith("0/elasticfog/robot_1/") for k in ros2_router.keys)
    assert not [k for k in ros2_router.keys if k.startswith("ef/")], ros2_router.keys
    # The router's peers: the observer, the SDK's session and the robot's ROS 2 session.
    assert len(list(ros2_router.session.info.peers_zid())) == 3
    assert "denied" not in robot.log_text().lower()
    robot.check_alive()


STEREO_MODEL = "zoo:stereo"
STEREO_SHAPE = [3, 120, 160]
LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
NEAR_WALL_M, FAR_WALL_M = 0.5, 6.0
STOP_MARGIN_M = 0.3
V_ASKED = 1.0


class StereoCamera:
    """Publishes a rendered stereo pair of a corridor closed by a wall (its distance settable)
    on two topics with their CameraInfos, at about 10 pairs a second, each image stamped now."""

    def __init__(self, peer: SdkPeer) -> None:
        from nav.camera import CameraModel
        from nav.render import StereoRenderer

        _, height, width = STEREO_SHAPE
        self.camera = CameraModel.for_image(width, height)
        self.renderer = StereoRenderer(self.camera, width, height, seed=3)
        self.peer = peer
        self.wall_m = NEAR_WALL_M
        self._pairs: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._pubs = {
            side: (
                peer.publisher(topic, "sensor_msgs/msg/Image"),
                peer.publisher(
                    topic.rsplit("/", 1)[0] + "/camera_info", "sensor_msgs/msg/CameraInfo"
                ),
            )
            for side, topic in (("left", LEFT), ("right", RIGHT))
        }
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stereo-camera", daemon=True)
        self._thread.start()

    def _pair(self) -> tuple[np.ndarray, np.ndarray]:
        from nav.render import Pose
        from nav.world import corridor_with_wall

        if self.wall_m not in self._pairs:
            world = corridor_with_wall(self.wall_m)
            self._pairs[self.wall_m] = self.renderer.pair(world, Pose(0.0, 0.0, math.pi / 2))
        return self._pairs[self.wall_m]

    def _run(self) -> None:
        _, height, width = STEREO_SHAPE
        baseline_px = -self.camera.fx_px * self.camera.baseline_m
        while not self._stop.wait(0.1):  # bounded by stop
            left, right = self._pair()
            stamp = time.time_ns()
            for side, image, skew, p3 in (("left", left, 0, 0.0), ("right", right, 2, baseline_px)):
                image_pub, info_pub = self._pubs[side]
                head = header(self.peer, stamp + skew * 1_000_000, f"{side}_optical")
                info = _camera_info(self.peer, height, width, p3)
                info["k"][0] = info["k"][4] = info["p"][0] = info["p"][5] = self.camera.fx_px
                info_pub.publish(header=head, **info)
                image_pub.publish(
                    header=head,
                    height=height,
                    width=width,
                    encoding="rgb8",
                    is_bigendian=0,
                    step=width * 3,
                    data=np.ascontiguousarray(image).reshape(-1),
                )

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def test_a_stereo_pair_on_two_topics_drives_nav_assist(
    tmp_path: Path, local_fleet: Any, sdk_peer: Any, e2e_cache: Path, ros2_router: Ros2Router
) -> None:
    load_partition(STEREO_MODEL, input_shape=tuple(STEREO_SHAPE))
    fleet = _fleet(
        tmp_path / "fleet",
        {
            "input_shape": STEREO_SHAPE,
            "deadline_s": 2.0,
            "ros2": {"endpoint": ros2_router.endpoint},
            "machines": {
                ROBOT: {
                    "source": f"ros2:{LEFT},right={RIGHT}",
                    "results": {"ros2": RESULTS},
                }
            },
        },
        tls=False,
        model=STEREO_MODEL,
    )
    lf = local_fleet(fleet)
    lf.start_registry()  # no cloud: the robot computes d_coll itself (--policy robot)
    peer = sdk_peer(ros2_router.port)
    safe: list[tuple[float, float]] = []
    cond = threading.Condition()

    def on_safe(msg: Any) -> None:
        with cond:
            safe.append((float(msg.linear.x), float(msg.angular.z)))
            cond.notify_all()

    peer.subscriber("/cmd_vel", "geometry_msgs/msg/Twist", on_safe)
    d_coll: list[Any] = []
    peer.subscriber(f"{RESULTS}/d_coll", "std_msgs/msg/Float32MultiArray", d_coll.append)
    robot = lf.start_robot(ROBOT, "--policy", "robot")
    assist = lf.procs.start(
        "assist",
        [
            "nav",
            "assist",
            "--config",
            str(fleet.config),
            "--robot",
            ROBOT,
            "--stop-margin",
            str(STOP_MARGIN_M),
        ],
    )
    camera = StereoCamera(peer)
    teleop = peer.publisher("/cmd_vel_teleop", "geometry_msgs/msg/Twist")
    vector = peer.types("geometry_msgs/msg/Vector3")

    def drive_until(good: Any, what: str) -> tuple[float, float]:
        deadline = time.monotonic() + WAIT_S
        while True:  # bounded by the deadline
            start = len(safe)
            teleop.publish(
                linear=vector(x=V_ASKED, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0)
            )
            with cond:
                cond.wait_for(lambda start=start: len(safe) > start, timeout=0.2)
            if len(safe) > start and good(safe[-1]):
                return safe[-1]
            assert time.monotonic() < deadline, (
                f"{what}: last {safe[-3:]}\n{robot.log_tail()}\n{assist.log_tail()}"
            )

    try:
        wait_until(lambda: d_coll or None, timeout_s=WAIT_S * 2, what="d_coll", procs=[robot])
        # A near wall: the command is slowed (the obstacle, not the deadline: d_coll flows).
        v, _ = drive_until(lambda c: c[0] < V_ASKED, "a near wall slows the command")
        wait_until(
            lambda: "-> obstacle" in assist.log_text() or None,
            timeout_s=WAIT_S,
            what="the assistant's obstacle limit",
            procs=[assist],
        )
        assert 0.0 <= v < V_ASKED
        # A far wall: the command passes unchanged.
        camera.wall_m = FAR_WALL_M
        assert drive_until(lambda c: c == (V_ASKED, 0.0), "a far wall passes the command")
    finally:
        camera.close()
    wait_until(
        lambda: "geometry from CameraInfo" in robot.log_text() or None,
        timeout_s=WAIT_S,
        what="the robot's geometry line",
        procs=[robot],
    )
    line = next(x for x in robot.log_text().splitlines() if "geometry from CameraInfo" in x)
    assert "baseline 0.0600 m" in line, line
    robot.check_alive()
    assist.check_alive()
