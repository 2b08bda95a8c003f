"""`results: {ros2: "<prefix>"}`: each applied frame's outputs on ROS 2 topics, over rmw_zenoh.

A result sink (`robotd.results.sinks`) of the robot's ROS 2 node (`robotd.ros2_node`: on the
robot's ROS 2 session when `ros2.endpoint` is set, else on its fleet session). Per applied frame:

- every model output on `<prefix>/<output name>` as `std_msgs/msg/Float32MultiArray` (its
  values as float32 in C order, one layout dimension per axis, labelled `axis0`, `axis1`, ...);
- an output of shape 1×1×H×W or H×W (a disparity or depth map) also as a 32FC1
  `sensor_msgs/msg/Image` on `<prefix>/<output name>/image`;
- an output of shape 1×N or N (N ≥ 2: a classifier's scores) also as
  `vision_msgs/msg/Classification` on `<prefix>/<output name>/classification`: the top 5
  classes, class_id the index as text, score its softmax probability;
- all outputs as one `isaac_ros_tensor_list_interfaces/msg/TensorList` on `<prefix>/tensors`
  (Isaac ROS's convention: name, rank and dims, data type code, byte strides, bytes), so Isaac
  ROS decoders read them;
- the model's view of the camera as `sensor_msgs/msg/CameraInfo` on `<prefix>/camera_info`:
  the model input's size, `roi` the rectangle of the camera image that was scaled to it (the
  crop of `robotd.sources.frame_sources.fit_crop`), and K and P the camera's (from its own
  CameraInfo, when it publishes one) cropped and scaled to that view, else zeros (uncalibrated).
  A pixel (u, v) of the model's input is the camera's (roi.x_offset + (u + 0.5)·roi.width/width
  − 0.5, roi.y_offset + (v + 0.5)·roi.height/height − 0.5).

Every message with a header carries the input frame's header (its capture stamp and frame id,
`robotd.ros2_node.input_frame`), so message_filters and tf pair a result with its image. A
Float32MultiArray has no header: the capture stamp is the source timestamp of every message's
rmw_zenoh attachment (what a ROS 2 subscriber reads as `MessageInfo.source_timestamp`). An
output name that is not a ROS 2 name token (`output.1`) has its other characters replaced by '_'
(`common.rmw_zenoh.name_token`); an output whose topic would be one of the others' is refused at
the first result with a one-line error.

Publishers are declared, with their MP liveliness tokens and the configured history depth
(`ros2.qos_depth`), when the first result comes (the output names and shapes are the model's);
messages are built by rosbags (`common.ros2_messages`) and published from the frame loop's
thread (a fraction of a millisecond at 640×480 for a classifier; a slow subscriber never blocks
it: rmw_zenoh's volatile, keep-last publishers drop).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from common import rmw_zenoh
from common.errors import UserError
from common.ros2_messages import (
    CameraInfo,
    Header,
    MessageType,
    Roi,
    encode_camera_info,
    encode_classification,
    encode_float32_multi_array,
    encode_image_32fc1,
    encode_tensor_list,
    is_class_scores,
    is_image_shaped,
    top_classes,
    typestore,
)
from robotd.ros2_node import InputFrame, Ros2Node, Ros2Publisher, acquire_robot_node, input_frame
from robotd.sources.frame_sources import fit_crop

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig
    from robotd.frame_path.frame import FrameResult

IMAGE_SUFFIX = "image"
CLASSIFICATION_SUFFIX = "classification"
TENSORS_TOPIC = "tensors"
CAMERA_INFO_TOPIC = "camera_info"


def results_topic(prefix: str, output: str) -> str:
    """`<prefix>/<output name as a ROS 2 name token>`."""
    return f"{prefix.rstrip('/')}/{rmw_zenoh.name_token(output)}"


def model_view_info(
    frame: InputFrame | None, header: Header, height: int, width: int
) -> CameraInfo:
    """The CameraInfo of the model's `height`×`width` view of `frame` (see the module
    docstring); a frame no ROS 2 source took is taken as already the model's size."""
    if frame is None:
        return CameraInfo(header, height, width, roi=Roi(0, 0, height, width))
    top, left, crop_h, crop_w = fit_crop(frame.height, frame.width, height, width)
    info = CameraInfo(header, height, width, roi=Roi(left, top, crop_h, crop_w))
    camera = frame.camera
    if camera is None or (camera.height, camera.width) != (frame.height, frame.width):
        return info  # no intrinsics, or those of another resolution than the frames'
    sx, sy = width / crop_w, height / crop_h
    k, p = camera.k, camera.p

    def x(value: float) -> float:  # a column of the camera image in the model's view
        return (value - left + 0.5) * sx - 0.5

    def y(value: float) -> float:
        return (value - top + 0.5) * sy - 0.5

    view_k = (k[0] * sx, k[1] * sx, x(k[2]), 0.0, k[4] * sy, y(k[5]), 0.0, 0.0, 1.0)
    view_p = (
        *(p[0] * sx, p[1] * sx, x(p[2]), p[3] * sx),
        *(0.0, p[5] * sy, y(p[6]), p[7] * sy),
        *(0.0, 0.0, 1.0, p[11]),
    )
    return replace(
        info, k=view_k, p=view_p, r=camera.r, d=camera.d, distortion_model=camera.distortion_model
    )


@dataclass
class _OutputPublishers:
    """The publishers of one output: its array, and where its shape calls for them, its 32FC1
    Image and its Classification."""

    array: Ros2Publisher
    image: Ros2Publisher | None
    classification: Ros2Publisher | None

    def close(self) -> None:
        for publisher in (self.array, self.image, self.classification):
            if publisher is not None:
                publisher.close()


class Ros2ResultSink:
    """Publishes each applied frame's outputs under a topic prefix (see the module docstring).
    `height`, `width`: the model input's size (its view of the camera)."""

    def __init__(
        self,
        cfg: FleetConfig,
        robot: str,
        session: zenoh.Session | None,
        prefix: str,
        *,
        height: int,
        width: int,
    ) -> None:
        self.prefix = rmw_zenoh.topic_name(prefix)
        self.height, self.width = height, width
        ros2 = cfg.ros2_for(robot)
        self.qos = rmw_zenoh.Qos(depth=ros2.qos_depth)
        self._node: Ros2Node = acquire_robot_node(cfg, robot, session)
        self.domain = self._node.node.domain
        store = typestore()
        self._types = {
            kind: rmw_zenoh.TopicType.of(kind.value, store)
            for kind in (
                MessageType.FLOAT32_MULTI_ARRAY,
                MessageType.IMAGE,
                MessageType.CLASSIFICATION,
                MessageType.TENSOR_LIST,
                MessageType.CAMERA_INFO,
            )
        }
        # Output name -> its publishers; made on the first result.
        self._outputs: dict[str, _OutputPublishers] = {}
        self._tensors: Ros2Publisher | None = None
        self._camera_info: Ros2Publisher | None = None
        self.published = 0
        # Frames whose 1×N output held a non-finite score: published without a Classification.
        self.unclassified = 0

    def _publisher(self, topic: str, kind: MessageType) -> Ros2Publisher:
        return self._node.publisher(topic, self._types[kind], self.qos)

    def _check_topics(self, result: FrameResult) -> None:
        """One line naming two things that would share a topic (an output named `tensors` or
        `camera_info`, two outputs whose names become the same token)."""
        owners = {
            f"{self.prefix.rstrip('/')}/{TENSORS_TOPIC}": "the TensorList",
            f"{self.prefix.rstrip('/')}/{CAMERA_INFO_TOPIC}": "the model view's CameraInfo",
        }
        for name in result.outputs:
            topic = results_topic(self.prefix, name)
            if topic in owners:
                raise UserError(
                    f"output {name!r} and {owners[topic]} would both be published on {topic}"
                )
            owners[topic] = f"output {name!r}"

    def _publishers_for(self, result: FrameResult) -> None:
        self._check_topics(result)
        base = self.prefix.rstrip("/")
        self._tensors = self._publisher(f"{base}/{TENSORS_TOPIC}", MessageType.TENSOR_LIST)
        self._camera_info = self._publisher(f"{base}/{CAMERA_INFO_TOPIC}", MessageType.CAMERA_INFO)
        for name, value in result.outputs.items():
            topic = results_topic(self.prefix, name)
            shape = np.shape(value)
            self._outputs[name] = _OutputPublishers(
                array=self._publisher(topic, MessageType.FLOAT32_MULTI_ARRAY),
                image=self._publisher(f"{topic}/{IMAGE_SUFFIX}", MessageType.IMAGE)
                if is_image_shaped(shape)
                else None,
                classification=self._publisher(
                    f"{topic}/{CLASSIFICATION_SUFFIX}", MessageType.CLASSIFICATION
                )
                if is_class_scores(shape)
                else None,
            )

    def publish(self, result: FrameResult) -> None:
        if self._tensors is None:
            self._publishers_for(result)
        assert self._tensors is not None and self._camera_info is not None
        stamp = result.stamp_ns
        frame = input_frame(stamp)
        header = Header(stamp, frame.header.frame_id if frame is not None else "")
        outputs = {name: v for name, v in result.outputs.items() if name in self._outputs}
        for name, value in outputs.items():
            # Not in `outputs`: an output the first frame did not have (not the model's).
            publishers = self._outputs[name]
            publishers.array.put(encode_float32_multi_array(value), stamp)
            if publishers.image is not None and is_image_shaped(value.shape):
                publishers.image.put(encode_image_32fc1(value, header), stamp)
            if publishers.classification is not None and is_class_scores(value.shape):
                if not np.all(np.isfinite(value)):
                    self.unclassified += 1  # scores with a NaN rank nothing: no message
                    continue
                hypotheses = top_classes(value)
                publishers.classification.put(encode_classification(hypotheses, header), stamp)
        self._tensors.put(encode_tensor_list(outputs, header), stamp)
        info = model_view_info(frame, header, self.height, self.width)
        self._camera_info.put(encode_camera_info(info), stamp)
        self.published += 1

    def close(self) -> None:
        for publishers in self._outputs.values():
            publishers.close()
        self._outputs.clear()
        for publisher in (self._tensors, self._camera_info):
            if publisher is not None:
                publisher.close()
        self._tensors = self._camera_info = None
        self._node.release()
