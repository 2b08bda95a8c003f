"""`results: {ros2: "<prefix>"}`: each applied frame's outputs on ROS 2 topics, over rmw_zenoh.

A result sink (`robotd.results.sinks`) of the robot's ROS 2 node (`robotd.ros2_node`): every model
output is published on `<prefix>/<output name>` as `std_msgs/msg/Float32MultiArray` (its values
as float32 in C order, one layout dimension per axis, labelled `axis0`, `axis1`, ...), and an
output of shape 1×1×H×W or H×W (a disparity or depth map) also as a 32FC1 `sensor_msgs/msg/Image`
on `<prefix>/<output name>/image` with the input frame's header (its capture stamp and frame id),
so RViz and Foxglove show it as it is. A Float32MultiArray has no header: the input frame's
capture stamp is the source timestamp of every message's rmw_zenoh attachment (what a ROS 2
subscriber reads as `MessageInfo.source_timestamp`), so each result can be matched to its frame.
An output name that is not a ROS 2 name token (`output.1`) has its other characters replaced by
'_' (`common.rmw_zenoh.name_token`).

Publishers are declared, with their MP liveliness tokens, when the first result comes (the
output names and shapes are the model's); messages are built by rosbags (`common.ros2_messages`)
and published from the frame loop's thread (serializing and handing a message to Zenoh takes a
fraction of a millisecond at 640×480; a slow subscriber never blocks it: rmw_zenoh's volatile,
keep-last publishers drop).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from common import rmw_zenoh
from common.errors import UserError
from common.ros2_messages import (
    Header,
    MessageType,
    encode_float32_multi_array,
    encode_image_32fc1,
    is_image_shaped,
    typestore,
)
from robotd.ros2_node import Ros2Node, Ros2Publisher, acquire_node

if TYPE_CHECKING:
    import zenoh

    from robotd.frame_path.frame import FrameResult

IMAGE_SUFFIX = "image"


def results_topic(prefix: str, output: str) -> str:
    """`<prefix>/<output name as a ROS 2 name token>`."""
    return f"{prefix.rstrip('/')}/{rmw_zenoh.name_token(output)}"


class Ros2ResultSink:
    """Publishes each applied frame's outputs under a topic prefix (see the module docstring)."""

    def __init__(self, session: zenoh.Session, domain: int, robot: str, prefix: str) -> None:
        self.prefix = rmw_zenoh.topic_name(prefix)
        self.domain = domain
        self._node: Ros2Node = acquire_node(session, domain, robot)
        array_type = MessageType.FLOAT32_MULTI_ARRAY.value
        self._array_type = rmw_zenoh.TopicType.of(array_type, typestore())
        self._image_type = rmw_zenoh.TopicType.of(MessageType.IMAGE.value, typestore())
        # Output name -> (its array publisher, its Image publisher or None); made on first use.
        self._publishers: dict[str, tuple[Ros2Publisher, Ros2Publisher | None]] = {}
        self.published = 0

    def _publishers_for(self, result: FrameResult) -> None:
        topics: dict[str, str] = {}
        for name, value in result.outputs.items():
            topic = results_topic(self.prefix, name)
            if topic in topics.values():
                raise UserError(
                    f"outputs {name!r} and {next(n for n, t in topics.items() if t == topic)!r} "
                    f"would both be published on {topic}"
                )
            topics[name] = topic
            array = self._node.publisher(topic, self._array_type, rmw_zenoh.DEFAULT_QOS)
            image = None
            if is_image_shaped(value.shape):
                image = self._node.publisher(
                    f"{topic}/{IMAGE_SUFFIX}", self._image_type, rmw_zenoh.DEFAULT_QOS
                )
            self._publishers[name] = (array, image)

    def publish(self, result: FrameResult) -> None:
        if not self._publishers:
            self._publishers_for(result)
        header = Header(result.stamp_ns, self._node.frame_id(result.stamp_ns))
        for name, value in result.outputs.items():
            publishers = self._publishers.get(name)
            if publishers is None:  # an output the first frame did not have: not the model's
                continue
            array, image = publishers
            array.put(encode_float32_multi_array(value), result.stamp_ns)
            if image is not None and is_image_shaped(value.shape):
                image.put(encode_image_32fc1(value, header), result.stamp_ns)
        self.published += 1

    def close(self) -> None:
        for array, image in self._publishers.values():
            array.close()
            if image is not None:
                image.close()
        self._publishers.clear()
        self._node.release()
