"""H.264 for camera images that cross at cut 0: one stream's encoder and decoder (PyAV, libx264).

Why: a camera's next frame is mostly its last one moved a little. JPEG codes each frame alone;
H.264 codes a P-frame as the difference from the picture before it, so a moving camera's frame
costs a twentieth of a JPEG at the same PSNR (docs/video.md). The price is state: a P-frame is
decodable only by a decoder that decoded the picture it is predicted from, so the robot keeps an
encoder per (service, deployment) (`robotd.frame_path.video_streams`) and each deployment a
decoder per robot (`cloudd.video_streams`), and the request says where the frame stands in its
stream (`common.wire.robot_to_cloud.VideoStream`: stream id, sequence number, keyframe).

Settings, fixed (the receiver needs none of them): libx264 `preset=superfast`, `tune=zerolatency`
(no lookahead, no frame threads: one packet out for each frame in, at once), no B-frames, one
reference frame (superfast's), one thread; 4:2:0 chroma (so sides must be even); quality by CRF
(`DEFAULT_CRF`, the fleet file's `video.crf`). A keyframe is an IDR picture with its SPS and PPS
in band: a fresh decoder can start from it. The decoder is FFmpeg's h264 with error concealment
off and errors made fatal (`err_detect=explode`): a picture it cannot decode exactly is an error
(`CorruptPayload`), never a concealed guess, and `max_pixels` holds it to the declared shape, so a
header claiming a huge picture cannot make it allocate one.

`H264Codec` is the codec `h264` of `common.wire.tensor_codecs`: used alone (`encode_tensor_as`,
`decode_encoded`) every tensor is a keyframe coded and decoded on its own, which is what a
stateless caller can check. Streams go through `H264Encoder` and `H264Decoder`.
"""

from __future__ import annotations

import fractions
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from common.wire.errors import CorruptPayload, ShapeMismatch

CODEC_H264 = "h264"
# CRF 24 (x264's scale, 0..51: lower is better): a moving camera's P-frames at the PSNR of
# JPEG 50 (CRF 23-24 at 320x240 and 640x480), about a thirteenth of its bytes (docs/video.md,
# benchmarks/video_bench.py).
DEFAULT_CRF = 24
MIN_CRF = 0
MAX_CRF = 51
# An H.264 picture's sides in pixels; 4:2:0 chroma needs them even.
MAX_VIDEO_SIDE_PX = 8192
_ENCODER_OPTIONS = {
    # superfast, not ultrafast: CABAC, the deblocking filter and adaptive quantization make a
    # moving camera's P-frames a third of ultrafast's at the same PSNR, for ~0.7 ms more encoding
    # at 640x480 (docs/video.md).
    "preset": "superfast",
    "tune": "zerolatency",
    "bframes": "0",
    "threads": "1",
}
# Frames are numbered, not timed: the encoder's rate control only needs a rate.
_TIME_BASE = fractions.Fraction(1, 30)
_FORMATS = {1: "gray", 3: "rgb24"}  # channels -> PyAV's frame format


def video_shape_ok(height: int, width: int, channels: int) -> bool:
    """Whether an H.264 stream can carry uint8 images of this size: gray or RGB, even sides up
    to MAX_VIDEO_SIDE_PX."""
    return (
        channels in _FORMATS
        and 2 <= height <= MAX_VIDEO_SIDE_PX
        and 2 <= width <= MAX_VIDEO_SIDE_PX
        and height % 2 == 0
        and width % 2 == 0
    )


def _av() -> Any:
    """PyAV, imported on first use: most processes never code video."""
    import av

    return av


class H264Encoder:
    """One stream's encoder for `height`×`width` images of `channels` (1 or 3) channels at `crf`.

    `encode(image, keyframe=...)` gives the frame's bytes (one access unit) and whether it is a
    keyframe (the first frame always is). Not thread-safe: its owner serializes the calls."""

    def __init__(self, height: int, width: int, channels: int, *, crf: int = DEFAULT_CRF) -> None:
        if not video_shape_ok(height, width, channels):
            raise ValueError(f"h264 cannot carry a {height}×{width}×{channels} image")
        if not MIN_CRF <= crf <= MAX_CRF:
            raise ValueError(f"crf must be in {MIN_CRF}..{MAX_CRF}, got {crf}")
        av = _av()
        self.shape = (height, width, channels)
        self.crf = crf
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height = width, height
        ctx.pix_fmt = "yuv420p"
        ctx.time_base = _TIME_BASE
        ctx.options = {**_ENCODER_OPTIONS, "crf": str(crf)}
        ctx.open()
        self._ctx = ctx
        self._format = _FORMATS[channels]
        self._keyframe = av.video.frame.PictureType.I
        self.frames = 0

    def encode(self, image: np.ndarray, *, keyframe: bool) -> tuple[bytes, bool]:
        """`image` (H×W×C or H×W uint8, this encoder's shape) coded as the stream's next frame:
        (its bytes, whether it is a keyframe)."""
        h, w, c = self.shape
        pixels = np.ascontiguousarray(image).reshape((h, w) if c == 1 else (h, w, c))
        frame = _av().VideoFrame.from_ndarray(pixels, format=self._format)
        frame.pts = self.frames
        if keyframe or self.frames == 0:
            frame.pict_type = self._keyframe
        packets = self._ctx.encode(frame)
        self.frames += 1
        if len(packets) != 1:  # zerolatency: one packet per frame, at once
            raise RuntimeError(f"libx264 gave {len(packets)} packets for one frame")
        packet = packets[0]
        return bytes(packet), bool(packet.is_keyframe)


class H264Decoder:
    """One stream's decoder for `height`×`width`×`channels` images. `decode(data)` decodes the
    stream's next frame; any error (`CorruptPayload`, `ShapeMismatch`) leaves the decoder
    unusable until a keyframe (`broken`). Not thread-safe: its owner serializes the calls."""

    def __init__(self, height: int, width: int, channels: int) -> None:
        if not video_shape_ok(height, width, channels):
            raise ValueError(f"h264 cannot carry a {height}×{width}×{channels} image")
        self.shape = (height, width, channels)
        self._format = _FORMATS[channels]
        self._ctx: Any = None
        self.broken = True  # nothing decoded yet: only a keyframe can start it

    def _open(self) -> None:
        av = _av()
        h, w, _ = self.shape
        ctx = av.CodecContext.create("h264", "r")
        ctx.thread_count = 1  # frame threads would hold pictures back
        # Errors are errors (no concealment), and no picture larger than the declared one.
        ctx.options = {"err_detect": "explode", "ec": "0", "max_pixels": str(h * w)}
        ctx.open()
        self._ctx = ctx

    def decode(self, data: bytes, *, keyframe: bool, where: str = "tensor") -> np.ndarray:
        """The picture of `data`, as H×W×C uint8. A keyframe starts the decoder afresh; a
        P-frame needs the decoder to be whole (`broken` False), which its owner checks first."""
        if keyframe:
            self._open()  # a fresh decoder: nothing of the old stream can leak into this one
        elif self.broken or self._ctx is None:
            raise CorruptPayload(f"{where}: an h264 P-frame without its reference picture")
        self.broken = True  # until this frame is decoded whole
        av = _av()
        if not data:
            raise CorruptPayload(f"{where}: empty h264 data")
        try:
            frames = self._ctx.decode(av.Packet(data))
        except (av.error.FFmpegError, ValueError) as exc:
            raise CorruptPayload(f"{where}: corrupt or truncated h264 ({_one_line(exc)})") from None
        if len(frames) != 1:
            raise CorruptPayload(f"{where}: h264 data holds {len(frames)} pictures, expected one")
        frame = frames[0]
        if keyframe and not frame.key_frame:
            raise CorruptPayload(f"{where}: h264 frame sent as a keyframe is not one")
        if getattr(frame, "is_corrupt", False):
            raise CorruptPayload(f"{where}: h264 picture decoded with errors")
        h, w, c = self.shape
        if (frame.height, frame.width) != (h, w):
            raise ShapeMismatch(
                f"{where}: h264 picture is {frame.height}×{frame.width}, the declared shape "
                f"is {h}×{w}"
            )
        image = frame.to_ndarray(format=self._format)
        self.broken = False
        return np.ascontiguousarray(image).reshape(h, w, c)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# PyAV's contexts are cheap to make (an encoder ~3 ms, a decoder ~0.2 ms), but a stateless
# caller (a keyframe coded alone) would make one per call: one per thread and shape is kept.
_LOCAL = threading.local()


def encode_keyframe(image: np.ndarray, shape: Sequence[int], crf: int = DEFAULT_CRF) -> bytes:
    """`image` as one keyframe of its own (a stream of one frame)."""
    h, w, c = (int(x) for x in shape)
    cache: dict[tuple[int, int, int, int], H264Encoder] = _LOCAL.__dict__.setdefault("enc", {})
    encoder = cache.get((h, w, c, crf))
    if encoder is None:
        encoder = cache[(h, w, c, crf)] = H264Encoder(h, w, c, crf=crf)
    data, _ = encoder.encode(image, keyframe=True)
    return data


def decode_keyframe(data: bytes, shape: Sequence[int], where: str = "tensor") -> np.ndarray:
    """The picture of a keyframe coded on its own; `CorruptPayload` for anything else (a
    P-frame needs its stream's decoder)."""
    h, w, c = (int(x) for x in shape)
    return H264Decoder(h, w, c).decode(data, keyframe=True, where=where)


__all__ = [
    "CODEC_H264",
    "DEFAULT_CRF",
    "MAX_CRF",
    "MIN_CRF",
    "H264Decoder",
    "H264Encoder",
    "decode_keyframe",
    "encode_keyframe",
    "video_shape_ok",
]
