"""The robot's video encoders: one stream per deployment it sends `h264` frames to, kept honest.

A P-frame is the difference from the picture before it in its stream, so it is decodable only
by the decoder that decoded that picture (`common.wire.video_codec`). The robot daemon runs one
service, so its encoders are per (service, deployment): `VideoEncoders` keeps one `_Stream` per
deployment the frames go to (the route's deployment, or each member of a round-robin pool: a
member's stream holds the frames sent to it, so the pool's turns need no keyframe). A stream's
next frame is a keyframe whenever its decoder may not hold its last picture:

- its first frame (a new stream: a deployment not sent to before);
- after a route change (a move, failover, another epoch: the new deployment never saw the
  stream, and a deployment sent back to in standby freed its decoder);
- after frames the robot served itself (another action, P), which broke the camera's sequence:
  the next frame sent is a keyframe, which the policy prices (`robotd.policies.elastic`);
- after a frame of the stream that may not have been decoded: refused (busy, an error), lost
  or timed out (`unseen`);
- when asked (`encode(..., keyframe=True)`): a frame the deployment could not decode
  (`need_keyframe`) is resent as a keyframe (`robotd.frame_path.offload.CloudCall`).

A keyframe starts a new stream number; frames are numbered in their stream (`VideoStream.seq`),
so a deployment refuses a P-frame whose predecessor it did not decode rather than answer from a
broken picture. Encoding runs on the frame loop's thread, a keyframe resend on the call's
thread: one lock serializes them.
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from common.wire.robot_to_cloud import VideoStream
from common.wire.tensor_codecs import EncodedTensor, image_hwc
from common.wire.video_codec import CODEC_H264, DEFAULT_CRF, H264Encoder

# Where frames go when the robot has heard of no route yet (the anycast key reaches whoever
# serves it).
UNKNOWN_DEPLOYMENT = ""


@dataclass
class _Stream:
    """One deployment's stream: its encoders (one per tensor), its number and position, and
    what makes its next frame a keyframe."""

    number: int
    epoch: int
    breaks: int
    encoders: dict[str, H264Encoder] = field(default_factory=dict)
    seq: int = 0  # frames coded so far
    last_frame: int = -1
    whole: bool = False  # False: the next frame must be a keyframe


class VideoEncoders:
    """`VideoEncoders(crf=24)`: `encode` a frame's image tensors for a deployment; `skipped`,
    `unseen` and `keyframe_due` keep the streams honest (see the module docstring)."""

    def __init__(self, *, crf: int = DEFAULT_CRF) -> None:
        self.crf = crf
        self._lock = threading.Lock()
        self._streams: dict[str, _Stream] = {}
        # Stream numbers start at a random point: a restarted robot's first stream is not taken
        # for the one its previous run left at a deployment.
        self._numbers = itertools.count(int.from_bytes(os.urandom(4), "big"))
        self._breaks = 0  # frames served without a video frame sent, so far
        self.keyframes = 0
        self.pframes = 0

    def keyframe_due(self, deployment: str | None, epoch: int) -> bool:
        """Whether the next frame sent to `deployment` at route epoch `epoch` is a keyframe."""
        with self._lock:
            stream = self._streams.get(deployment or UNKNOWN_DEPLOYMENT)
            return stream is None or self._key_needed(stream, epoch)

    def _key_needed(self, stream: _Stream, epoch: int) -> bool:
        return not stream.whole or stream.epoch != epoch or stream.breaks != self._breaks

    def skipped(self) -> None:
        """A frame was served without sending a video frame (P, or another codec): every
        stream's next frame is a keyframe."""
        with self._lock:
            self._breaks += 1

    def unseen(self, deployment: str | None, video: VideoStream) -> None:
        """A frame of `video`'s stream may not have been decoded (refused, lost, timed out): the
        stream's next frame is a keyframe (nothing if the stream was already replaced)."""
        with self._lock:
            stream = self._streams.get(deployment or UNKNOWN_DEPLOYMENT)
            if stream is not None and stream.number == video.stream:
                stream.whole = False

    def encode(
        self,
        frame: int,
        deployment: str | None,
        epoch: int,
        images: Mapping[str, np.ndarray],
        *,
        keyframe: bool = False,
    ) -> tuple[dict[str, EncodedTensor], VideoStream]:
        """Frame `frame`'s image tensors coded as the next frame of `deployment`'s stream at
        route epoch `epoch` (a keyframe when due, or when `keyframe`): the tensors and where
        they stand in the stream."""
        where = deployment or UNKNOWN_DEPLOYMENT
        with self._lock:
            stream = self._streams.get(where)
            key = keyframe or stream is None or self._key_needed(stream, epoch)
            if stream is None or key:
                old = stream
                stream = _Stream(number=next(self._numbers), epoch=epoch, breaks=self._breaks)
                if old is not None:  # an encoder is kept with its shape (making one is ~3 ms)
                    stream.encoders = old.encoders
                self._streams[where] = stream
            tensors = {}
            for name, image in images.items():
                encoder = self._encoder(stream, name, image)
                data, was_key = encoder.encode(image, keyframe=key)
                # libx264 may also start a keyframe on its own (a scene cut, every 250 frames):
                # a P-frame's decoder takes it as it takes any frame of the stream.
                if key and not was_key:
                    raise RuntimeError("libx264 did not make the keyframe asked for")
                tensors[name] = EncodedTensor(
                    codec=CODEC_H264, dtype="uint8", shape=list(image.shape), data=data
                )
            video = VideoStream(stream=stream.number, seq=stream.seq, keyframe=key)
            stream.seq += 1
            stream.last_frame = frame
            stream.whole = True
            if key:
                self.keyframes += 1
            else:
                self.pframes += 1
            return tensors, video

    def _encoder(self, stream: _Stream, name: str, image: np.ndarray) -> H264Encoder:
        hwc = image_hwc(image.shape)
        if hwc is None:
            raise ValueError(f"tensor {name!r} of shape {list(image.shape)} is not an image")
        encoder = stream.encoders.get(name)
        if encoder is None or encoder.shape != hwc:
            encoder = stream.encoders[name] = H264Encoder(*hwc, crf=self.crf)
        return encoder

    def forget(self) -> None:
        """Drop every stream (its next frame anywhere is a keyframe)."""
        with self._lock:
            self._streams.clear()
