"""`ros2:<left>,right=<right>[,slop_ms=N]`: a stereo camera from its two ROS 2 image topics.

A stereo driver publishes its left and right images on two topics, each with its header stamp,
and their CameraInfos on the sibling `camera_info` topics. The robot's node subscribes to both
(`robotd.sources.ros2.ImageTopic`: any type and hash heard, the wrong ones named) and pairs the
images by header stamp, approximately as message_filters' ApproximateTime does for a pair: an
image is paired with the other side's waiting image nearest in stamp when they are at most
`slop_ms` apart (default 10 ms), at once (a camera's next pair comes a period later). Images
that can no longer be paired (older than a pair made, or pushed out of the short wait) are
dropped and counted (`unpaired`); an image not newer than its side's last (a stamp out of order
or repeated) is refused by name (`StampOutOfOrder`). Pairs then follow camera semantics
(`robotd.sources.newest_frame`): the newest pair waits for the frame loop, a pair it replaces
is counted in `dropped_stale`.

Both views are decoded as they arrive (pairing needs the stamps), fitted to the model's input
with one crop and scale (a rectified pair stays rectified) and handed on as a `StereoFrame`
(views `left`, `right`: zoo:stereo's inputs); the left header's stamp is the frame's capture
stamp. Geometry (`geometry()`): fx, cx, cy from the left camera's CameraInfo and the baseline
from the right camera's projection (P[3] = −fx·B), in pixels of the model's view; a right
camera whose P[3] is not negative is a named error (`BadCameraInfo`) and the last good geometry
is kept. Given the camera the model was built for (`built_for`, its metadata `nav.camera`), a
geometry that differs from it by more than 2% on fx or the baseline is one warning naming both
and the fleet file's `nav: camera:` lines for this camera (`robotd.sources.stereo_geometry`);
the source serves on. `StereoPairing` is the pairing alone, drivable from a test without sessions.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from common.ros2_messages import (
    BadCameraInfo,
    CameraInfo,
    Ros2MessageError,
    StampedFrame,
    decode_frame,
)
from common.wire.errors import ErrorCode
from robotd.ros2_node import InputFrame, acquire_robot_node, remember_frame
from robotd.sources.frame_sources import EndOfStream, FrameSource, fit_crop, fit_frame
from robotd.sources.newest_frame import NewestFrame
from robotd.sources.ros2 import (
    FRAME_MESSAGES,
    CameraInfoWatch,
    ImageTopic,
    Refusals,
    release_topics,
)
from robotd.sources.stereo_frame import LEFT_VIEW, RIGHT_VIEW, STEREO_VIEWS, StereoFrame
from robotd.sources.stereo_geometry import ModelCamera, StereoGeometry, mismatch_warning

if TYPE_CHECKING:
    from common.source_spec import Ros2Spec
    from robotd.sources.frame_sources import SourceSession

log = logging.getLogger("robotd.ros2")

NS_PER_MS = 1_000_000
# Images a side keeps waiting for its partner: a few camera periods.
MAX_WAITING = 4


class StampOutOfOrder(Ros2MessageError):
    """An image whose header stamp is not after its side's previous one."""

    code = ErrorCode.BAD_VALUE


@dataclass(frozen=True)
class StereoPair:
    """A left and a right image taken together."""

    left: StampedFrame
    right: StampedFrame


class StereoPairing:
    """Left and right images in, pairs out (see the module docstring). Not thread-safe: the
    caller serializes `add`."""

    def __init__(self, slop_ns: int, max_waiting: int = MAX_WAITING) -> None:
        self.slop_ns = slop_ns
        self.max_waiting = max_waiting
        self._waiting: dict[str, deque[StampedFrame]] = {LEFT_VIEW: deque(), RIGHT_VIEW: deque()}
        self._last: dict[str, int | None] = {LEFT_VIEW: None, RIGHT_VIEW: None}
        self.paired = 0
        self.unpaired = 0

    def add(self, side: str, frame: StampedFrame) -> StereoPair | None:
        """Take `side`'s image; the pair it makes, or None. StampOutOfOrder for an image not
        newer than its side's previous one (it is not kept)."""
        stamp = frame.stamp_ns
        last = self._last[side]
        if last is not None and stamp <= last:
            raise StampOutOfOrder(
                f"{side} image stamped {stamp} ns, not after the previous {side} one ({last} ns)"
            )
        self._last[side] = stamp
        other = RIGHT_VIEW if side == LEFT_VIEW else LEFT_VIEW
        waiting = self._waiting[other]
        best = min(waiting, key=lambda f: abs(f.stamp_ns - stamp), default=None)
        if best is None or abs(best.stamp_ns - stamp) > self.slop_ns:
            own = self._waiting[side]
            own.append(frame)
            self._drop_older(other, stamp - self.slop_ns)
            while len(own) > self.max_waiting:
                own.popleft()
                self.unpaired += 1
            return None
        # Everything older than the pair on either side can no longer be paired.
        while waiting and waiting[0] is not best:
            waiting.popleft()
            self.unpaired += 1
        waiting.popleft()
        self._drop_older(side, stamp)
        self.paired += 1
        left, right = (frame, best) if side == LEFT_VIEW else (best, frame)
        return StereoPair(left, right)

    def _drop_older(self, side: str, before_ns: int) -> None:
        """Drop `side`'s waiting images stamped before `before_ns`: no partner can come."""
        waiting = self._waiting[side]
        while waiting and waiting[0].stamp_ns < before_ns:
            waiting.popleft()
            self.unpaired += 1


def stereo_geometry(left: CameraInfo, right: CameraInfo, height: int, width: int) -> StereoGeometry:
    """The geometry of a pair whose images are fitted to `height`×`width` (fit_frame's crop and
    scale), from the left camera's K and the right camera's P; BadCameraInfo as the module
    docstring says."""
    baseline = right.baseline_m()
    top, left_px, crop_h, crop_w = fit_crop(left.height, left.width, height, width)
    sx, sy = width / crop_w, height / crop_h
    if left.fx <= 0:
        raise BadCameraInfo(f"the left camera's fx is {left.fx}")
    return StereoGeometry(
        fx_px=left.fx * sx,
        cx_px=(left.cx - left_px + 0.5) * sx - 0.5,
        cy_px=(left.cy - top + 0.5) * sy - 0.5,
        baseline_m=baseline,
    )


class Ros2StereoSource(FrameSource):
    """Stereo frames from two ROS 2 image topics (see the module docstring)."""

    views = STEREO_VIEWS

    def __init__(
        self,
        spec: Ros2Spec,
        session: SourceSession,
        stop: threading.Event | None = None,
        *,
        height: int,
        width: int,
        built_for: ModelCamera | None = None,
    ) -> None:
        assert spec.right is not None
        self.spec = spec
        self.height, self.width = height, width
        self.built_for = built_for
        self.message = FRAME_MESSAGES[spec.type]
        self.pairing = StereoPairing(round(spec.slop_ms * NS_PER_MS))
        self.taken = 0
        self._stop = stop if stop is not None else session.stop
        self._lock = threading.Lock()
        self._pairs = NewestFrame[StereoPair]()
        self._geometry: StereoGeometry | None = None
        self._node = acquire_robot_node(
            session.config, session.robot, session.session, domain=spec.domain
        )
        self.domain = self._node.node.domain
        self.description = (
            f"ros2 stereo {spec.topic} + {spec.right} ({self.message.value}, domain "
            f"{self.domain}, slop {spec.slop_ms:g} ms)"
        )
        self.refusals = Refusals(lambda: self.description)
        self._entities: list[ImageTopic | CameraInfoWatch] = []
        try:
            for side, topic in ((LEFT_VIEW, spec.topic), (RIGHT_VIEW, spec.right)):
                self._entities.append(
                    ImageTopic(
                        self._node,
                        topic,
                        self.message,
                        self.refusals,
                        functools.partial(self._on_image, side),
                    )
                )
            self.cameras = {
                LEFT_VIEW: CameraInfoWatch(self._node, spec.topic, self.refusals),
                RIGHT_VIEW: CameraInfoWatch(self._node, spec.right, self.refusals),
            }
            self._entities.extend(self.cameras.values())
        except BaseException:
            self._release()
            raise

    def _on_image(self, side: str, payload: bytes) -> None:
        # Called on a Zenoh callback thread by ImageTopic, which names what is raised here.
        frame = decode_frame(self.message, payload)
        with self._lock:
            pair = self.pairing.add(side, frame)
        if pair is not None:
            self._pairs.put(pair)

    def geometry(self) -> StereoGeometry | None:
        """The pair's geometry from its CameraInfos in the model's view; None before both came.
        A bad one is refused by name once per CameraInfo and the last good geometry kept."""
        left, right = self.cameras[LEFT_VIEW].info, self.cameras[RIGHT_VIEW].info
        if left is None or right is None:
            return self._geometry
        try:
            geometry = stereo_geometry(left, right, self.height, self.width)
        except BadCameraInfo as exc:
            self.refusals.refuse(exc, f"CameraInfo on {self.cameras[RIGHT_VIEW].topic}")
            self.cameras[RIGHT_VIEW].info = None
            return self._geometry
        if geometry != self._geometry:
            log.info(
                "%s: geometry from CameraInfo: fx %.1f px, cx %.1f, cy %.1f (model view "
                "%dx%d), baseline %.4f m",
                self.description,
                geometry.fx_px,
                geometry.cx_px,
                geometry.cy_px,
                self.width,
                self.height,
                geometry.baseline_m,
            )
            self._geometry = geometry
            self._check_built_for(geometry)
        return geometry

    def _check_built_for(self, geometry: StereoGeometry) -> None:
        """One warning when the model was built for another camera (module docstring)."""
        if self.built_for is None:
            return
        warning = mismatch_warning(geometry, self.built_for, height=self.height, width=self.width)
        if warning is not None:
            log.warning("%s: %s", self.description, warning)

    @property
    def unpaired(self) -> int:
        return self.pairing.unpaired

    @property
    def refused(self) -> dict[str, int]:
        return dict(self.refusals.by_name)

    def wait_ready(self, timeout_s: float) -> bool:
        return self._pairs.wait_ready(timeout_s, self._stop)

    def rejected_frames(self) -> dict[str, int]:
        return dict(self.refusals.by_code)

    def read(self) -> StereoFrame:
        pair = self._pairs.take(self._stop)
        self.dropped_stale = self._pairs.dropped_stale
        if pair is None:
            raise EndOfStream
        self.geometry()
        self.taken += 1
        self.last_stamp_ns = pair.left.stamp_ns
        height, width = pair.left.image.shape[:2]
        camera = self.cameras[LEFT_VIEW].info
        remember_frame(InputFrame(pair.left.header, height, width, camera))
        views = {
            LEFT_VIEW: fit_frame(pair.left.image, self.height, self.width),
            RIGHT_VIEW: fit_frame(pair.right.image, self.height, self.width),
        }
        return StereoFrame(views, pair.left.stamp_ns / 1e9 if pair.left.stamp_ns else time.time())

    def _release(self) -> None:
        release_topics(self._entities, self._node)

    def close(self) -> None:
        self.dropped_stale = self._pairs.dropped_stale
        self._pairs.close()
        self._release()
        log.info(
            "%s: %d pairs taken, %d dropped as stale, %d images unpaired, %s",
            self.description,
            self.taken,
            self.dropped_stale,
            self.pairing.unpaired,
            self.refusals.summary(),
        )
