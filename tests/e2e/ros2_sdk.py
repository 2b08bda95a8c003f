"""zenoh-ros2-sdk as the ROS 2 peer of the e2e tests: a pure-Python rmw_zenoh this project did not
write (its own CDR, type hashing and graph discovery), and the `.msg` files it reads.

The SDK looks for `.msg` files in a local folder (`get_registry(DIR)`) and would otherwise try to
download them: `write_messages` writes the ones the tests need, as upstream defines them (ROS 2
Jazzy's, vision_msgs 4.1.1's, Isaac ROS's tensor list; comments left out). The SDK computes the
types' RIHS01 hashes from these files itself, so a topic it and the robot agree on is a check of
the robot's hashes. The fixtures (`sdk_messages`, `sdk_peer`) are in this tier's conftest.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

# The .msg files the SDK needs, as upstream defines them (comments left out).
MSG_FILES = {
    "builtin_interfaces/msg/Time.msg": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header.msg": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "sensor_msgs/msg/Image.msg": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/msg/CompressedImage.msg": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "std_msgs/msg/MultiArrayDimension.msg": "string label\nuint32 size\nuint32 stride\n",
    "std_msgs/msg/MultiArrayLayout.msg": "MultiArrayDimension[] dim\nuint32 data_offset\n",
    "std_msgs/msg/Float32MultiArray.msg": "MultiArrayLayout layout\nfloat32[] data\n",
    "geometry_msgs/msg/Vector3.msg": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Twist.msg": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/msg/TwistStamped.msg": "std_msgs/Header header\nTwist twist\n",
    "sensor_msgs/msg/RegionOfInterest.msg": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/msg/CameraInfo.msg": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nRegionOfInterest roi\n"
    ),
    # vision_msgs 4.1.1 (ros-perception/vision_msgs, the ros2 branch: Jazzy's).
    "vision_msgs/msg/ObjectHypothesis.msg": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/Classification.msg": "std_msgs/Header header\nObjectHypothesis[] results\n",
    # Isaac ROS 4.4 (NVIDIA-ISAAC-ROS/isaac_ros_common, isaac_ros_tensor_list_interfaces).
    "isaac_ros_tensor_list_interfaces/msg/TensorShape.msg": "uint8 rank\nuint32[] dims\n",
    "isaac_ros_tensor_list_interfaces/msg/Tensor.msg": (
        "string name\nTensorShape shape\nint32 data_type\nuint64[] strides\nuint8[] data\n"
    ),
    "isaac_ros_tensor_list_interfaces/msg/TensorList.msg": (
        "std_msgs/Header header\nTensor[] tensors\n"
    ),
}


def write_messages(root: Path) -> Path:
    """The .msg files above under `root`, registered with the SDK before it looks for any."""
    from zenoh_ros2_sdk import get_registry

    for name, text in MSG_FILES.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    registry = get_registry(str(root))
    assert registry.messages_dir == root, "the SDK's registry was made before this fixture"
    return root


class SdkPeer:
    """The SDK's (process-wide) session on a router (the fleet's, or a ROS 2 graph's own), and
    what it declared."""

    def __init__(self, port: int) -> None:
        from zenoh_ros2_sdk import ZenohSession

        self.port = port
        self.session = ZenohSession.get_instance("127.0.0.1", port)
        self.entities: list[Any] = []

    def publisher(self, topic: str, msg_type: str) -> Any:
        from zenoh_ros2_sdk import ROS2Publisher

        pub = ROS2Publisher(topic, msg_type, node_name="camera", router_port=self.port)
        self.entities.append(pub)
        return pub

    def subscriber(self, topic: str, msg_type: str, callback: Any) -> Any:
        from zenoh_ros2_sdk import ROS2Subscriber

        sub = ROS2Subscriber(topic, msg_type, callback, node_name="planner", router_port=self.port)
        self.entities.append(sub)
        return sub

    def types(self, msg_type: str) -> Any:
        return self.session.store.types[msg_type]

    def close(self) -> None:
        from zenoh_ros2_sdk import ZenohSession, get_registry

        for entity in reversed(self.entities):
            entity.close()
        self.session.close()
        # The SDK keeps one session (with its type store) per process, and its registry notes
        # which types it put in that store: the next test's peer starts both afresh.
        ZenohSession._instance = None
        get_registry()._loaded_types.clear()


def header(peer: SdkPeer, stamp_ns: int, frame_id: str = "camera_optical") -> Any:
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    time_type = peer.types("builtin_interfaces/msg/Time")
    return peer.types("std_msgs/msg/Header")(
        stamp=time_type(sec=sec, nanosec=nanosec), frame_id=frame_id
    )
