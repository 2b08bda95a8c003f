"""Messages a robot sends to the deployment serving it, on its anycast service key
(`keys.svc_infer`). The deployment answers with a message of `cloud_to_robot`.

The cut's tensors travel as `EncodedTensor` records, each naming its codec (`tensor_codecs`): the
robot picks per tensor (`encode_tensor_as(array, "int8+zstd")`, or `EncodedTensor.raw(array)`),
the deployment decodes them with `decode_tensors(request.tensors, max_bytes=...)`.

A video codec's tensors (`h264`) belong to a stream: the request's `video` field says which and
where (`VideoStream`), and the deployment decodes them with that stream's decoder
(`cloudd.video_streams`), answering `need_keyframe` when its decoder does not hold the picture
a P-frame is predicted from."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from common.wire.codec import Message, Struct, key_path, register
from common.wire.tensor_codecs import EncodedTensor, check_encoded, is_video


@dataclass(frozen=True, slots=True, kw_only=True)
class VideoStream(Struct):
    """Where a request's video tensors stand in their stream: `stream` names the robot's
    encoder (a new number for each encoder it makes), `seq` counts the stream's frames from 0,
    `keyframe` says the frame starts the stream afresh (an IDR picture). A P-frame (`keyframe`
    false) decodes only at a decoder that decoded frame `seq - 1` of the same stream."""

    stream: int
    seq: int
    keyframe: bool

    def __post_init__(self) -> None:
        self._check_non_negative("stream", "seq")


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class InferRequest(Message):
    """Run the suffix after cut `cut` of the model `model_digest` on `tensors` (the cut's tensors
    by name, each encoded with its codec) and reply within `deadline_s` of `sent_at`.

    `deadline_s` is a budget, not a time of day: hosts' clocks are not synchronised, so the
    deployment measures it from the request's arrival (a request that waited in its queue longer
    than its budget is not computed: the robot has already finished the frame itself).
    `sent_at` is the robot's wall clock at sending, carried for telemetry only. `epoch` is the
    route epoch the robot believes in (0 before it heard of any route).

    `end_cut` (segment offload): run only the segment from `cut` to cut `end_cut` and reply with
    `end_cut`'s tensors by name (lossless; the robot runs the rest). Absent or nil: to the
    model's outputs, as a deployment that does not know the field does anyway.

    `video`: the stream position of the request's video tensors (`h264`); present exactly when
    some tensor is a video codec's.
    """

    TYPE: ClassVar[str] = "infer_request"
    robot: str
    frame: int
    model_digest: str
    cut: int
    tensors: dict[str, EncodedTensor]
    deadline_s: float
    sent_at: float
    epoch: int = 0
    end_cut: int | None = None
    video: VideoStream | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot")
        self._check_non_negative("frame", "cut", "epoch")
        if self.end_cut is not None and not self.end_cut > self.cut:
            raise self._invalid(
                "end_cut", f"must be after the cut ({self.cut}), got {self.end_cut}"
            )
        self._check_finite("deadline_s", "sent_at")
        self._check_positive("deadline_s")
        if not self.model_digest:
            raise self._invalid("model_digest", "must not be empty")
        if not self.tensors:
            raise self._invalid("tensors", "at least one tensor is needed")
        for name, tensor in self.tensors.items():
            if not isinstance(tensor, EncodedTensor):  # e.g. a bare ndarray from older code
                raise self._invalid(
                    "tensors",
                    f"{name!r} is a {type(tensor).__name__}, expected an EncodedTensor "
                    "(EncodedTensor.raw(array) or encode_tensor_as(array, codec))",
                )
            # Codec, dtype, shape, data length and int8 parameters, before any data is decoded.
            check_encoded(tensor, key_path(f"{self.TYPE}.tensors", name))
        video = [name for name, tensor in self.tensors.items() if is_video(tensor.codec)]
        if video and self.video is None:
            raise self._invalid(
                "video", f"tensor(s) {', '.join(video)} are video: the stream position is needed"
            )
        if self.video is not None and not video:
            raise self._invalid("video", "given, but no tensor is a video codec's")
