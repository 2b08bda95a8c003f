"""`source: zenoh`: frames an application publishes on `ef/<fleet>/in/<robot>`.

Each sample is one `FrameIn` (`common.wire.app_to_robot`): a capture stamp and, per image input,
a JPEG/PNG image or raw rgb8/bgr8/mono8 rows. The robot reads frames as a camera gives them:
always the newest. The subscriber's callback only keeps the sample's bytes in a one-frame slot;
a frame still waiting there when a newer one arrives is dropped and counted (`dropped_stale`),
never silently lost. Decoding happens in `read()`, on the frame loop's thread (a Zenoh callback
must stay short): a frame that cannot be decoded (not a `FrameIn`, a corrupt image, images that
do not match the model's inputs) is one throttled line naming its error and is counted by error
code (`rejected`); the source then waits for the next frame. Nothing an application sends can
end the source: only the daemon's stop (SIGINT/SIGTERM) or `--frames` does.

Frames are fitted to the model's input size as the `photo` source fits its photographs
(`robotd.sources.frame_sources.fit_frame`): the largest centred rectangle of the model's aspect is
kept and scaled with area interpolation when it shrinks (linear when it grows). The frame's stamp is
its message's `stamp_ns` (0: unknown, the robot stamps it when it reads it).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from typing import TYPE_CHECKING

import numpy as np
import zenoh

from common import keys
from common.throttled_log import ThrottledLog
from common.wire import WireError
from common.wire.app_to_robot import FrameIn, ImageIn, decode_image
from common.wire.errors import ErrorCode, InvalidValue
from robotd.sources.frame_sources import MAX_SOURCE_SIDE_PX, EndOfStream, FrameSource, fit_frame
from robotd.sources.stereo_frame import CameraFrame, StereoFrame

if TYPE_CHECKING:
    from robotd.sources.frame_sources import SourceSession

log = logging.getLogger("robotd")

# How often a read waiting for a frame looks at the stop flag.
STOP_POLL_S = 0.1


class ZenohSource(FrameSource):
    """Frames from `ef/<fleet>/in/<robot>` at `height`×`width`; `views` the model's image inputs
    when it has several (a stereo pair, matched by name), None for one."""

    def __init__(
        self,
        where: SourceSession,
        *,
        height: int,
        width: int,
        views: tuple[str, ...] | None = None,
    ) -> None:
        self.height, self.width = height, width
        self.views = views
        self.robot = where.robot
        self.key = keys.frames_in(where.config.fleet, where.robot)
        self.description = f"zenoh {self.key} ({width}x{height})"
        self.max_bytes = where.config.max_payload_bytes
        self.received = 0
        self.rejected: Counter[str] = Counter()
        self._stop = where.stop or threading.Event()
        self._ready = threading.Condition()
        self._waiting: bytes | None = None
        self._closed = False
        self._throttled = ThrottledLog(log, label=lambda: f"robot {self.robot}")
        self._subscriber = where.session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Keep the newest frame's bytes; one still waiting is dropped and counted. A payload
        over the limit is refused here, before it is copied."""
        size = len(sample.payload)
        if size > self.max_bytes:
            with self._ready:
                self.received += 1
                self.rejected[ErrorCode.TOO_LARGE.value] += 1
            self._throttled.warning(
                "%s: frame on %s rejected (%s): %d bytes exceed the limit of %d",
                self.robot,
                self.key,
                ErrorCode.TOO_LARGE.value,
                size,
                self.max_bytes,
            )
            return
        data = sample.payload.to_bytes()
        with self._ready:
            self.received += 1
            if self._waiting is not None:
                self.dropped_stale += 1
            self._waiting = data
            self._ready.notify()

    def read(self) -> CameraFrame:
        while True:  # bounded by the stop flag: each wait is STOP_POLL_S at most
            data = self._next()
            try:
                return self._decode(data)
            except WireError as exc:
                with self._ready:
                    self.rejected[exc.code.value] += 1
                self._throttled.warning(
                    "%s: frame on %s rejected (%s): %s",
                    self.robot,
                    self.key,
                    exc.code.value,
                    exc.reason,
                )

    def wait_ready(self, timeout_s: float) -> bool:
        with self._ready:
            if self._waiting is None and not self._closed and not self._stop.is_set():
                self._ready.wait(timeout_s)
            # Stopping: read() ends the stream at once.
            return self._waiting is not None or self._closed or self._stop.is_set()

    def _next(self) -> bytes:
        with self._ready:
            while self._waiting is None:
                if self._closed or self._stop.is_set():
                    raise EndOfStream
                self._ready.wait(STOP_POLL_S)
            data, self._waiting = self._waiting, None
            return data

    def _decode(self, data: bytes) -> CameraFrame:
        message = FrameIn.from_wire(data, max_bytes=self.max_bytes)
        images = message.images
        if self.views is None:
            if len(images) != 1:
                raise InvalidValue(
                    f"frame_in.images: the model takes one image, the frame has {len(images)} "
                    f"({', '.join(images)})"
                )
            ((name, image),) = images.items()
            frame: CameraFrame = self._fitted(image, name)
        else:
            if sorted(images) != sorted(self.views):
                raise InvalidValue(
                    f"frame_in.images: the model's image inputs are {', '.join(self.views)}, "
                    f"the frame has {', '.join(images)}"
                )
            stamp_s = (message.stamp_ns or time.time_ns()) / 1e9
            frame = StereoFrame(
                {view: self._fitted(images[view], view) for view in self.views}, stamp_s
            )
        self.last_stamp_ns = message.stamp_ns or None
        return frame

    def _fitted(self, image: ImageIn, name: str) -> np.ndarray:
        bgr = decode_image(
            image,
            max_side_px=MAX_SOURCE_SIDE_PX,
            max_bytes=self.max_bytes,
            fit=(self.height, self.width),
            where=f"frame_in.images.{name}",
        )
        return fit_frame(bgr, self.height, self.width)

    def rejected_frames(self) -> dict[str, int]:
        with self._ready:
            return dict(self.rejected)

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify_all()
        self._subscriber.undeclare()


__all__ = ["ZenohSource"]
