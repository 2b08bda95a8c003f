"""A small client for applications: send a robot camera frames and read its results.

    from robotd.results.client import RobotClient

    with RobotClient("fleet.yaml", "robot-1") as robot:
        stamp = robot.send(image)                 # uint8 BGR H×W×3 (OpenCV's layout)
        for result in robot.results(timeout=2.0):  # each applied frame, as it comes
            print(result.frame, result.served_by, result.outputs["logits"].argmax())
        result = robot.infer(image, timeout=2.0)   # send, then wait for that frame's result

It uses only the two keys of the contract (`common.keys`): it publishes `FrameIn` messages on
`ef/<fleet>/in/<robot>` (read by a robot whose source is `zenoh`) and subscribes to
`FrameResultMessage`s on `ef/<fleet>/out/<robot>` (every robot publishes them), so any Zenoh
client in any language can do the same (docs/wire.md has the layout). A result is matched to
its frame by the capture stamp the client sent, which the robot carries back unchanged; the
client makes each stamp it picks larger than the last.

The session is a Zenoh client of the fleet's router (the registry's endpoint) unless told
otherwise; an unreachable endpoint is a UserError naming it. Results wait in a bounded queue
(`max_queued`): when the application does not read them, the oldest are dropped and counted
(`dropped`). Close the client (or use it as a context manager): a session left open at exit
hangs the process.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from common import keys
from common.wire import WireError, decode_tensors
from common.wire.app_to_robot import FrameIn, ImageEncoding, ImageIn, image_in
from common.wire.robot_to_app import FrameResultMessage, ServedBy

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig

# How long a client session keeps trying to reach the router before the client gives up.
CONNECT_TIMEOUT_S = 2.0
DEFAULT_QUEUE = 64
DEFAULT_TIMEOUT_S = 5.0
# The image name of a frame for a one-input model (the robot takes it whatever its name).
MONO_IMAGE = "image"


@dataclass(frozen=True)
class Result:
    """One applied frame's result: the message's fields and the outputs decoded."""

    message: FrameResultMessage
    outputs: dict[str, np.ndarray]
    received_ns: int

    @property
    def frame(self) -> int:
        return self.message.frame

    @property
    def stamp_ns(self) -> int:
        return self.message.stamp_ns

    @property
    def served_by(self) -> ServedBy:
        return self.message.served_by

    @property
    def latency_s(self) -> float:
        return self.message.latency_s


class RobotClient:
    """`RobotClient(config, robot)`: `config` is a fleet file (path) or a loaded FleetConfig;
    `robot` one of its robots. `encoding` (jpeg, png, rgb8, bgr8, mono8) and `quality` are how
    `send` encodes images. `mode`/`connect` override the session (default: a client of the
    registry's endpoint); `identity` is the TLS identity (default: the CLI's certificate)."""

    def __init__(
        self,
        config: FleetConfig | str | Path,
        robot: str,
        *,
        encoding: ImageEncoding | str = ImageEncoding.JPEG,
        quality: int = 0,
        max_queued: int = DEFAULT_QUEUE,
        mode: str = "client",
        connect: list[str] | None = None,
        identity: str | None = None,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
    ) -> None:
        from common.config import CLI_IDENTITY, FleetConfig, load_fleet
        from common.session import open_session

        cfg = config if isinstance(config, FleetConfig) else load_fleet(Path(config))
        cfg.machine(robot, role=keys.Role.ROBOT)  # a UserError naming the robots when there is none
        self.config, self.robot = cfg, robot
        self.encoding = ImageEncoding(encoding)
        self.quality = quality
        self.max_bytes = cfg.max_payload_bytes
        self.dropped = 0
        self.rejected = 0
        self._last_stamp_ns = 0
        self._lock = threading.Lock()
        self._queue: queue.Queue[Result] = queue.Queue(max_queued)
        self.in_key = keys.frames_in(cfg.fleet, robot)
        self.out_key = keys.results_out(cfg.fleet, robot)
        self.session: zenoh.Session = open_session(
            cfg,
            mode=mode,
            listen=[],
            connect=connect if connect is not None else [cfg.registry.endpoint],
            connect_timeout_s=connect_timeout_s,
            identity=identity or CLI_IDENTITY,
        )
        try:
            import zenoh

            self._subscriber = self.session.declare_subscriber(self.out_key, self._on_result)
            self._publisher = self.session.declare_publisher(
                self.in_key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        except Exception:
            self.session.close()
            raise

    def wait_for_robot(self, timeout: float = DEFAULT_TIMEOUT_S) -> bool:
        """Wait until a robot subscribes to this client's frames (its `zenoh` source is
        open); False when none did within `timeout` seconds. Frames sent before are lost to
        no one: nobody reads them."""
        ready = threading.Event()

        def on_status(status: object) -> None:
            if getattr(status, "matching", False):
                ready.set()

        listener = self._publisher.declare_matching_listener(on_status)
        try:
            # zenoh's stubs type matching_status as a bool; it is a MatchingStatus.
            if self._publisher.matching_status.matching:  # type: ignore[attr-defined]
                return True
            return ready.wait(timeout)
        finally:
            listener.undeclare()

    # -- sending ---------------------------------------------------------------------------
    def send(
        self, image: np.ndarray | Mapping[str, np.ndarray] | FrameIn, stamp: int | None = None
    ) -> int:
        """Send one frame: an image (uint8 BGR H×W×3, or grey H×W), the named views of a stereo
        pair, or a ready `FrameIn`; `stamp` is its capture stamp (ns since the epoch; default:
        now, made larger than the last one sent). Returns the stamp, which the frame's result
        carries back."""
        if isinstance(image, FrameIn):
            message = image
        else:
            stamp_ns = self._stamp(stamp)
            views = {MONO_IMAGE: image} if isinstance(image, np.ndarray) else dict(image)
            images = {name: self._image(view) for name, view in views.items()}
            message = FrameIn(stamp_ns=stamp_ns, images=images)
        self._publisher.put(message.to_wire())
        return message.stamp_ns

    def _image(self, image: np.ndarray) -> ImageIn:
        return image_in(image, self.encoding, quality=self.quality)

    def _stamp(self, stamp: int | None) -> int:
        with self._lock:
            if stamp is None:
                stamp = max(time.time_ns(), self._last_stamp_ns + 1)
            self._last_stamp_ns = max(self._last_stamp_ns, stamp)
            return stamp

    # -- receiving -------------------------------------------------------------------------
    def _on_result(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        try:
            message = FrameResultMessage.from_wire(
                sample.payload.to_bytes(), max_bytes=self.max_bytes
            )
            outputs = decode_tensors(message.outputs, max_bytes=self.max_bytes, where="outputs")
        except WireError:
            self.rejected += 1
            return
        result = Result(message, outputs, received_ns)
        while True:  # at most two tries: the queue has one free slot after a drop
            try:
                self._queue.put_nowait(result)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def results(self, timeout: float | None = DEFAULT_TIMEOUT_S) -> Iterator[Result]:
        """Each result as it comes, in the order received; ends when none came within
        `timeout` seconds (None: waits for ever, e.g. until the application is interrupted)."""
        while True:  # bounded by `timeout` between results
            try:
                yield self._queue.get(timeout=timeout)
            except queue.Empty:
                return

    def infer(
        self, image: np.ndarray | Mapping[str, np.ndarray], timeout: float = DEFAULT_TIMEOUT_S
    ) -> Result:
        """Send `image`, then wait for its result (older results waiting are passed over).
        TimeoutError when it does not come within `timeout` seconds: the robot may not be
        running with `source: zenoh`, or dropped the frame for a newer one another sender
        sent."""
        stamp = self.send(image)
        deadline = time.monotonic() + timeout
        while True:  # bounded by the deadline
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                result = self._queue.get(timeout=left)
            except queue.Empty:
                break
            if result.stamp_ns == stamp:
                return result
        raise TimeoutError(
            f"no result for the frame stamped {stamp} from robot {self.robot} within "
            f"{timeout:g} s (is it running with source: zenoh?)"
        )

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> None:
        """Undeclare and close the session."""
        try:
            self._subscriber.undeclare()
            self._publisher.undeclare()
        finally:
            self.session.close()

    def __enter__(self) -> RobotClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["Result", "RobotClient"]
