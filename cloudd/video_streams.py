"""A deployment's video decoders: one stream per robot of a service, decoded in order, bounded.

A robot's `h264` frames form a stream (`common.wire.robot_to_cloud.VideoStream`); a P-frame is
decodable only by the decoder that decoded the frame before it (`common.wire.video_codec`). So
each robot in service here has one decoder per video tensor, decoded at admission, on the
service key's callback thread, in the order the frames arrive (the workers run batches in any
order). What is decoded and how:

- a keyframe starts the robot's stream afresh (a new decoder: nothing of the old picture
  leaks in), whatever stream it names;
- a P-frame is decoded only if it is the next frame (`seq`) of the stream whose last frame
  this decoder decoded whole; anything else (another stream, a gap, a decoder freed, or broken
  by an earlier error) is refused `need_keyframe` (`NeedKeyframe`), and the robot resends the
  frame as a keyframe or finishes it itself: never a result from a broken picture;
- a frame the decoder cannot decode (corrupt or truncated data, a picture of another size) is
  the codec's error (`corrupt_payload`, `shape_mismatch`), and the stream needs a keyframe.

Decoders are keyed by the robot of the service key the frame came on (the admission has
refused a body naming another robot, `wrong_robot`): a robot cannot feed or reset another
robot's stream. Memory is bounded: at most `max_streams` robots hold decoders (~2 MB each at
640×480; a new robot's keyframe takes the place of the one idle longest, which then needs a
keyframe), a stream idle for `idle_s` is freed, and a robot's stream is freed when it leaves
service here (`forget`, called on standby).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from common.config import DEFAULT_MAX_VIDEO_STREAMS, DEFAULT_VIDEO_IDLE_S
from common.partition import TensorSpec
from common.wire import NeedKeyframe
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import image_hwc, is_video
from common.wire.video_codec import H264Decoder


@dataclass
class _RobotStream:
    """One robot's stream here: its number, the last frame decoded whole, its decoders."""

    number: int
    seq: int
    used_at: float
    decoders: dict[str, H264Decoder] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)


class VideoDecoders:
    """The video streams of one service plane (see the module docstring)."""

    def __init__(
        self,
        *,
        max_streams: int = DEFAULT_MAX_VIDEO_STREAMS,
        idle_s: float = DEFAULT_VIDEO_IDLE_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_streams < 1 or idle_s <= 0:
            raise ValueError("max_streams must be >= 1 and idle_s > 0")
        self.max_streams = max_streams
        self.idle_s = idle_s
        self._clock = clock
        self._lock = threading.Lock()
        self._streams: OrderedDict[str, _RobotStream] = OrderedDict()  # least recent first
        self.evicted = 0  # streams freed to make room for another robot's
        self.expired = 0  # streams freed after idle_s

    def __len__(self) -> int:
        with self._lock:
            return len(self._streams)

    def robots(self) -> list[str]:
        """The robots holding a stream here, least recently used first."""
        with self._lock:
            return list(self._streams)

    def forget(self, robot: str) -> None:
        """Free `robot`'s stream (it left service here)."""
        with self._lock:
            self._streams.pop(robot, None)

    def decode(
        self, robot: str, request: InferRequest, specs: Sequence[TensorSpec]
    ) -> dict[str, np.ndarray]:
        """The video tensors of `request` (which `check_request` passed for this model), decoded
        as the next frame of `robot`'s stream: {name: array of the spec's shape}. Raises
        `NeedKeyframe`, or the codec's `CorruptPayload`/`ShapeMismatch` (the stream then needs
        a keyframe)."""
        video = request.video
        assert video is not None  # a request with video tensors has it (InferRequest)
        now = self._clock()
        stream = self._take(robot, video.keyframe, video.stream, now)
        if stream is None:
            raise NeedKeyframe(
                f"frame {request.frame} of {robot}: a P-frame, but no decoder here holds "
                f"{robot}'s stream: send a keyframe"
            )
        with stream.lock:
            if video.keyframe:
                stream.decoders.clear()  # fresh decoders: nothing of the old stream leaks in
            elif stream.seq < 0 or stream.number != video.stream or video.seq != stream.seq + 1:
                raise NeedKeyframe(self._gap(robot, stream, request))
            stream.seq = -1  # broken until this frame is decoded whole
            out = {
                spec.name: self._decode_one(stream, spec, request, video.keyframe)
                for spec in specs
                if is_video(request.tensors[spec.name].codec)
            }
            stream.number, stream.seq, stream.used_at = video.stream, video.seq, now
            return out

    def _decode_one(
        self, stream: _RobotStream, spec: TensorSpec, request: InferRequest, keyframe: bool
    ) -> np.ndarray:
        enc = request.tensors[spec.name]
        hwc = image_hwc(enc.shape)
        assert hwc is not None  # check_encoded: h264 applies to this shape
        decoder = stream.decoders.get(spec.name)
        if decoder is None or decoder.shape != hwc:
            if not keyframe:
                raise NeedKeyframe(f"tensor {spec.name!r}: no decoder holds its stream")
            decoder = stream.decoders[spec.name] = H264Decoder(*hwc)
        image = decoder.decode(bytes(enc.data), keyframe=keyframe, where=spec.name)
        return image.reshape(enc.shape)

    def _take(self, robot: str, keyframe: bool, number: int, now: float) -> _RobotStream | None:
        """`robot`'s stream; for a keyframe of a robot without one, a new one (in the place of
        the stream idle longest when all are taken); None for a P-frame of a robot without one.
        Idle streams are freed first."""
        with self._lock:
            self._expire(now)
            stream = self._streams.get(robot)
            if stream is not None:
                self._streams.move_to_end(robot)
                stream.used_at = now
                return stream
            if not keyframe:
                return None
            if len(self._streams) >= self.max_streams:
                self._streams.popitem(last=False)
                self.evicted += 1
            stream = self._streams[robot] = _RobotStream(number=number, seq=-1, used_at=now)
            return stream

    def _expire(self, now: float) -> None:
        while self._streams:
            robot, oldest = next(iter(self._streams.items()))
            if now - oldest.used_at < self.idle_s:
                return
            del self._streams[robot]
            self.expired += 1

    @staticmethod
    def _gap(robot: str, stream: _RobotStream, request: InferRequest) -> str:
        video = request.video
        assert video is not None
        if stream.seq < 0:
            held = "no picture of its stream"
        elif stream.number != video.stream:
            held = f"stream {stream.number}, not {video.stream}"
        else:
            held = f"frame {stream.seq} of its stream, not {video.seq - 1}"
        return (
            f"frame {request.frame} of {robot}: a P-frame (stream {video.stream}, frame "
            f"{video.seq}) but this decoder holds {held}: send a keyframe"
        )
