"""Frame sources of the robot daemon.

A source yields uint8 BGR frames (H×W×3, OpenCV's layout) one at a time, or stereo frames:

- `synthetic[:key=F][,every=N]`: seeded frames with controllable entropy. Key frames are
  textured (noise, gradients and blocks: normalized grey-level entropy near 1); the others are
  flat (one grey level with a little noise: entropy near 0.2). `key=F` draws each frame as a key
  frame with probability F (default 0.25, from the seed); `every=N` makes every N-th frame a key
  frame instead. The same seed gives the same frames, so runs can be compared.
- `photo[:NAME][,motion=pan|zoom|shake|mixed][,speed=F]`: real photographs shipped inside the
  scikit-image wheel (nothing is downloaded) seen through a moving virtual camera: each frame is a
  view of the photograph with a smooth pan, a slow zoom in and out and a small hand shake (one
  `cv2.warpAffine` per frame), resized to the source's size. Without NAME the photographs take
  turns, a scene change every `PHOTO_SCENE_FRAMES` (100) frames, so the content, and hence the
  JPEG size, varies like a camera's; with NAME the camera stays on that photograph. `motion`
  picks which movements are made (default `mixed`: all three) and `speed=F` scales their pace
  (default 1; 0 is a still camera). The same seed gives the same frames.
- `video:PATH[,loop=false]`: a video file read with OpenCV, played at the file's own frame rate
  (its timeline, `next_offset_s`, unless `--fps` is given) and looped at its end (a file stands
  in for a camera, so `--frames N` is honoured whatever the file's length); with `loop=false` the
  run ends at the end of the file.
- `bag:PATH[:TOPIC]`: a rosbag2 recording's image topic, at its recorded rate
  (`robotd.sources.bag`).
- `camera:N` or `camera:/dev/videoN`: the camera with index N through OpenCV (on Linux the
  device /dev/videoN).
- `zenoh`: frames an application publishes on `ef/<fleet>/in/<robot>` (`robotd.sources.zenoh_in`),
  the newest first (older waiting frames are dropped and counted), fitted to the model's size
  like the photographs (`fit_frame`).
- `stereo:...`: a stereo pair a frame (`nav.stereo_sources`: a rendered world, the Motorcycle
  pair, two image files, a scripted maneuver); its frames are
  `robotd.sources.stereo_frame.StereoFrame`s of named views.

The specs' grammar is `common.source_spec` (parsed once into a typed value);
`robotd.sources.opening` opens a parsed spec. A source that cannot be opened is a `SourceError` (a
`UserError`) naming it. A source may end (`EndOfStream`) and may take each served frame's result
(`on_result`, after the daemon's own). A source fed over Zenoh (`zenoh`, `ros2:`:
`SourceSpec.needs_session`) is opened with the daemon's session (`SourceSession`), once that is
open; opened without one it is a
`SourceError`.
`common.image_input.InputAdapter` turns a frame into the model's input; the photographs
themselves are `common.photos`.
"""

from __future__ import annotations

import abc
import contextlib
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from common.photos import PHOTOS, photo_bgr
from common.source_spec import PHOTO, SYNTHETIC, CameraMotion, SourceError, motion_names
from robotd.sources.stereo_frame import CameraFrame

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig
    from robotd.frame_path.frame import FrameResult

DEFAULT_KEY_FRACTION = 0.25
# Flat frames: one grey level, moving slowly, with noise of this amplitude (grey levels): a few
# histogram bins are used, so the normalized entropy stays around 0.2-0.3.
FLAT_NOISE_LEVELS = 3
KEY_BLOCKS = 12
CAMERA_READ_TRIES = 3
# Without a NAME the camera moves to the next photograph every this many frames.
PHOTO_SCENE_FRAMES = 100
# At zoom 1 the view covers this share of the largest rectangle of the frame's aspect that fits in
# the photograph: the rest is room to pan.
PHOTO_BASE_VIEW = 0.75
# The slow zoom goes from 1 to this (the view shrinks by it) and back.
PHOTO_ZOOM_MAX = 1.35
PHOTO_ZOOM_PERIOD_FRAMES = 240.0
# The pan: two sinusoids per axis (periods in frames, amplitudes as shares of the room to pan).
PHOTO_PAN_PERIODS_FRAMES = (240.0, 90.0)
PHOTO_PAN_WEIGHTS = (0.8, 0.2)
# Hand shake: a translation of about this many output pixels and a rotation of this many degrees,
# at a few hertz at 30 frames/s (periods in frames).
PHOTO_SHAKE_PX = 1.0
PHOTO_SHAKE_DEG = 0.2
PHOTO_SHAKE_PERIODS_FRAMES = (7.0, 11.0)
PHOTO_SHAKE_ROT_PERIOD_FRAMES = 7.1
# Periods are varied by up to this share per scene, so no two scenes move alike.
PHOTO_PERIOD_JITTER = 0.2
MAX_PHOTO_SPEED = 20.0
MAX_SOURCE_SIDE_PX = 8192
# `fit_frame` low-pass filters before it shrinks from this ratio on (anti-aliasing), not below it.
AREA_SHRINK = 2.0
# The low-pass filter's sigma per unit of shrink: one-pixel stripes shrunk 480 -> 224 keep a
# std of 9 levels of 255 (area interpolation: 8.5; no filter: 75).
ANTI_ALIAS_SIGMA = 0.35
# A video container claiming more frames per second than this has no real frame rate (some give
# their clock's tick rate, e.g. 90000).
MAX_VIDEO_FPS = 1000.0


class EndOfStream(Exception):
    """Raised by `read()` of a source that has no more frames: the robot's frame loop ends as
    it does after `--frames` (frames in flight finish, the daemon stops cleanly)."""


@dataclass(frozen=True)
class SourceSession:
    """What a source fed over Zenoh needs from the robot daemon: its open session (whose
    lifetime covers the source's: the source is released first), the fleet's config and the
    robot's id (the keys it listens on are the robot's)."""

    session: zenoh.Session
    config: FleetConfig
    robot: str
    # The daemon's stop flag: a source waiting for frames ends (EndOfStream) once it is set.
    stop: threading.Event | None = None


class FrameSource(abc.ABC):
    """Yields uint8 BGR frames (H×W×3), or stereo frames of named views; `close()` releases the
    device or file."""

    description: str = "source"
    views: tuple[str, ...] | None = None
    """The names of a stereo source's views (`robotd.sources.stereo_frame`); None: one image a
    frame."""
    last_stamp_ns: int | None = None
    """The capture stamp (ns since the epoch) of the frame `read()` returned last, where the
    source knows it (a camera message's header, a bag record); None: the robot stamps the frame
    with its own clock when it reads it."""
    dropped_stale: int = 0
    """Frames the source dropped, unread, because a newer one arrived first (a source fed by
    others at their own rate, e.g. `zenoh`: the robot works on the newest frame); counted in
    each frame's telemetry and the run summary."""

    @abc.abstractmethod
    def read(self) -> CameraFrame:
        """The next frame; SourceError when none can be read."""

    def wait_ready(self, timeout_s: float) -> bool:
        """Whether `read()` has a frame without waiting, after waiting up to `timeout_s` for
        one (a source fed by others at their pace); True for sources that make their frames."""
        return True

    def next_offset_s(self) -> float | None:
        """Seconds from the source's first frame to the one `read()` returns next, on the
        source's own timeline (a video's frame times, a bag's record times), or None: the source
        has no timeline (or no next frame) and the robot paces it at the configured fps. The
        robot plays a source with a timeline at that pace unless `--fps` is given."""
        return None

    def rejected_frames(self) -> dict[str, int]:
        """Frames received but not decodable, by error code (a source fed by others, a
        recording's damaged records)."""
        return {}

    def on_result(self, result: FrameResult) -> None:  # noqa: B027 - most sources ignore it
        """Frame `result.frame` (the n-th frame read, from 0) was served and applied: a source
        whose frames depend on what the robot computed (`nav.maneuver_source`) takes it."""

    def close(self) -> None:  # noqa: B027 - sources without resources need nothing
        """Release what the source holds."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SyntheticSource(FrameSource):
    """Seeded frames: textured key frames among flat ones (see the module docstring)."""

    def __init__(
        self,
        height: int,
        width: int,
        *,
        seed: int = 0,
        key_fraction: float = DEFAULT_KEY_FRACTION,
        key_every: int | None = None,
    ) -> None:
        _check_size(height, width)
        if not 0.0 <= key_fraction <= 1.0 or not math.isfinite(key_fraction):
            raise SourceError(f"synthetic source: key must be in [0, 1], got {key_fraction}")
        if key_every is not None and key_every < 1:
            raise SourceError(f"synthetic source: every must be >= 1, got {key_every}")
        self.height, self.width = height, width
        self.seed = seed
        self.key_fraction = key_fraction
        self.key_every = key_every
        self.index = 0
        self._rng = np.random.default_rng(seed)
        every = f", every={key_every}" if key_every else f", key={key_fraction:g}"
        self.description = f"synthetic {width}x{height} (seed {seed}{every})"

    def read(self) -> np.ndarray:
        n = self.index
        self.index += 1
        if self.key_every is not None:
            key = n % self.key_every == 0
        else:
            key = bool(self._rng.random() < self.key_fraction)
        return self._key_frame() if key else self._flat_frame(n)

    def _key_frame(self) -> np.ndarray:
        h, w, rng = self.height, self.width, self._rng
        frame = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        # Blocks of random colour over the noise: structure as well as texture.
        for _ in range(KEY_BLOCKS):
            y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
            y1 = min(h, y0 + int(rng.integers(1, max(2, h // 3))))
            x1 = min(w, x0 + int(rng.integers(1, max(2, w // 3))))
            colour = rng.integers(0, 256, size=3, dtype=np.uint8)
            frame[y0:y1, x0:x1] = (frame[y0:y1, x0:x1] // 2) + (colour // 2)
        return frame

    def _flat_frame(self, n: int) -> np.ndarray:
        # A slowly drifting grey level, as a camera facing a wall in changing light.
        level = 96 + int(32 * math.sin(n / 25.0))
        noise = self._rng.integers(
            -FLAT_NOISE_LEVELS, FLAT_NOISE_LEVELS + 1, size=(self.height, self.width, 1)
        )
        grey = np.clip(level + noise, 0, 255).astype(np.uint8)
        return np.repeat(grey, 3, axis=2)


class PhotoSource(FrameSource):
    """Photographs seen through a moving virtual camera (see the module docstring).

    Frame `n` depends only on the seed and `n`: the scene (which photograph, in an order drawn
    from the seed) is `n // PHOTO_SCENE_FRAMES`, and the camera's path in a scene is a sum of
    sinusoids whose phases and periods are drawn from (seed, scene). The photographs are loaded
    and scaled down to about the frame's size when the source opens; a frame is then one
    `cv2.warpAffine` (a fraction of a millisecond at 320×240).
    """

    def __init__(
        self,
        height: int,
        width: int,
        *,
        seed: int = 0,
        name: str | None = None,
        motion: CameraMotion | str = CameraMotion.MIXED,
        speed: float = 1.0,
    ) -> None:
        _check_size(height, width, kind=PHOTO)
        if name is not None and name not in PHOTOS:
            raise SourceError(f"photo source: unknown photo {name!r}; known: {', '.join(PHOTOS)}")
        try:
            self.motion = CameraMotion(motion)
        except ValueError:
            raise SourceError(
                f"photo source: motion must be one of {motion_names()}, got {motion!r}"
            ) from None
        if not 0.0 <= speed <= MAX_PHOTO_SPEED or not math.isfinite(speed):
            raise SourceError(
                f"photo source: speed must be in [0, {MAX_PHOTO_SPEED:g}], got {speed}"
            )
        if seed < 0:
            raise SourceError(f"photo source: seed must be >= 0, got {seed}")
        self.height, self.width = height, width
        self.seed, self.name, self.speed = seed, name, speed
        self.index = 0
        if name is None:
            order = np.random.default_rng(seed).permutation(len(PHOTOS))
            self.names = [list(PHOTOS)[int(i)] for i in order]
        else:
            self.names = [name]
        self._photos = [self._fit(photo_bgr(n)) for n in self.names]
        self._scene: tuple[int, CameraPath] | None = None
        shown = name or "all photos"
        self.description = (
            f"photo {shown} {width}x{height} (seed {seed}, motion={self.motion.value}, "
            f"speed={speed:g})"
        )

    def scene(self, n: int) -> int:
        """The scene frame `n` belongs to (always 0 with a NAME: the camera stays on it)."""
        return n // PHOTO_SCENE_FRAMES if self.name is None else 0

    def photo_name(self, n: int) -> str:
        """The photograph frame `n` shows."""
        return self.names[self.scene(n) % len(self.names)]

    def read(self) -> np.ndarray:
        frame = self.frame_at(self.index)
        self.index += 1
        return frame

    def frame_at(self, n: int) -> np.ndarray:
        """Frame `n` of this source (what the `n`-th `read()` returns)."""
        scene = self.scene(n)
        if self._scene is None or self._scene[0] != scene:
            # One independent stream per scene (a child of the seed's), so any frame can be made
            # without drawing those before it.
            stream = np.random.SeedSequence(self.seed, spawn_key=(scene,))
            self._scene = (scene, CameraPath(np.random.default_rng(stream)))
        path = self._scene[1]
        photo = self._photos[scene % len(self._photos)]
        t = (n - scene * PHOTO_SCENE_FRAMES) * self.speed  # frames since the scene began
        matrix = path.view(t, self.motion, photo.shape[0], photo.shape[1], self.height, self.width)
        return warp_view(photo, matrix, self.height, self.width)

    def _fit(self, photo: np.ndarray) -> np.ndarray:
        return fit_photo(photo, self.height, self.width)


def fit_photo(photo: np.ndarray, height: int, width: int) -> np.ndarray:
    """The photograph scaled down (area interpolation, once) so that a `height`×`width` view at
    zoom 1 maps about one photo pixel to one frame pixel: warping then never shrinks by much, so
    it needs no anti-aliasing. Photographs smaller than that are kept and magnified."""
    view_w = PHOTO_BASE_VIEW * fit_rect(photo.shape[0], photo.shape[1], height, width)[1]
    factor = width / view_w
    if factor >= 1.0:
        return photo
    size = (max(1, round(photo.shape[1] * factor)), max(1, round(photo.shape[0] * factor)))
    return cv2.resize(photo, size, interpolation=cv2.INTER_AREA)


def warp_view(photo: np.ndarray, matrix: np.ndarray, height: int, width: int) -> np.ndarray:
    """The `height`×`width` view of `photo` through `matrix` (`CameraPath.view`)."""
    return cv2.warpAffine(
        photo,
        matrix,
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        # Shake and rotation may reach a pixel or two past the photograph's edge: mirror it
        # rather than show black corners.
        borderMode=cv2.BORDER_REFLECT_101,
    )


class CameraPath:
    """The virtual camera's movement during one scene, drawn from `rng` (the `photo` source's,
    and the stereo pair source's, which moves both views alike)."""

    def __init__(self, rng: np.random.Generator) -> None:
        def periods(base: tuple[float, ...]) -> list[float]:
            jitter = rng.uniform(1 - PHOTO_PERIOD_JITTER, 1 + PHOTO_PERIOD_JITTER, len(base))
            return [p * float(j) for p, j in zip(base, jitter, strict=True)]

        self.pan_periods = [periods(PHOTO_PAN_PERIODS_FRAMES) for _ in range(2)]
        self.pan_phases = rng.uniform(0, 2 * math.pi, (2, len(PHOTO_PAN_PERIODS_FRAMES)))
        # Where the camera points when it does not pan, as a share of the room to pan (x, y).
        self.still = rng.uniform(-0.6, 0.6, 2)
        self.zoom_period = periods((PHOTO_ZOOM_PERIOD_FRAMES,))[0]
        self.zoom_phase = float(rng.uniform(0, 2 * math.pi))
        self.shake_periods = [periods(PHOTO_SHAKE_PERIODS_FRAMES) for _ in range(2)]
        self.shake_phases = rng.uniform(0, 2 * math.pi, (2, len(PHOTO_SHAKE_PERIODS_FRAMES)))
        self.rot_period = periods((PHOTO_SHAKE_ROT_PERIOD_FRAMES,))[0]
        self.rot_phase = float(rng.uniform(0, 2 * math.pi))

    def view(
        self, t: float, motion: CameraMotion, photo_h: int, photo_w: int, height: int, width: int
    ) -> np.ndarray:
        """The 2×3 affine map from frame pixels to photograph pixels at time `t` (frames)."""
        mixed = motion is CameraMotion.MIXED
        zoom = 1.0
        if mixed or motion is CameraMotion.ZOOM:
            wave = 0.5 - 0.5 * math.cos(2 * math.pi * t / self.zoom_period + self.zoom_phase)
            zoom += (PHOTO_ZOOM_MAX - 1.0) * wave
        rect_h, rect_w = fit_rect(photo_h, photo_w, height, width)
        view_h, view_w = PHOTO_BASE_VIEW * rect_h / zoom, PHOTO_BASE_VIEW * rect_w / zoom
        aim = [float(v) for v in self.still]
        if mixed or motion is CameraMotion.PAN:
            aim = [
                sum(
                    w * math.sin(2 * math.pi * t / p + float(phase))
                    for w, p, phase in zip(
                        PHOTO_PAN_WEIGHTS,
                        self.pan_periods[axis],
                        self.pan_phases[axis],
                        strict=True,
                    )
                )
                for axis in range(2)
            ]
        cx = (photo_w - 1) / 2 + aim[0] * (photo_w - view_w) / 2
        cy = (photo_h - 1) / 2 + aim[1] * (photo_h - view_h) / 2
        scale = view_w / width  # photograph pixels per frame pixel
        angle = 0.0
        if mixed or motion is CameraMotion.SHAKE:
            shake = [
                sum(
                    w * math.sin(2 * math.pi * t / p + float(phase))
                    for w, p, phase in zip(
                        (0.6, 0.4), self.shake_periods[axis], self.shake_phases[axis], strict=True
                    )
                )
                for axis in range(2)
            ]
            cx += PHOTO_SHAKE_PX * shake[0] * scale
            cy += PHOTO_SHAKE_PX * shake[1] * scale
            angle = math.radians(PHOTO_SHAKE_DEG) * math.sin(
                2 * math.pi * t / self.rot_period + self.rot_phase
            )
        a, b = scale * math.cos(angle), scale * math.sin(angle)
        qx, qy = (width - 1) / 2, (height - 1) / 2
        return np.array(
            [[a, -b, cx - (a * qx - b * qy)], [b, a, cy - (b * qx + a * qy)]], dtype=np.float64
        )


def fit_frame(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """`image` at `height`×`width` as the photo source frames a photograph: the largest centred
    rectangle of the frame's aspect is kept (nothing is stretched), then scaled linearly, after
    a low-pass filter when it shrinks by `AREA_SHRINK` or more (what anti-aliasing needs; below
    that, as the photo source's warp: a JPEG decoded at a reduced DCT scale is within 2x of the
    model's size). The filter is a box average at a whole ratio (OpenCV's area interpolation,
    exact and fast there) and else a Gaussian of sigma `ANTI_ALIAS_SIGMA` × ratio, which damps
    one-pixel stripes as much as area interpolation does: that one, at a ratio such as 480 → 224,
    costs twice as much (1.4 ms against 0.66 ms on one core), a third of a ROS 2 frame's whole way
    in. An image of that size is returned as it is."""
    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image
    top, left, crop_h, crop_w = fit_crop(h, w, height, width)
    view = image[top : top + crop_h, left : left + crop_w]
    shrink = min(crop_h / height, crop_w / width)
    if shrink >= AREA_SHRINK:
        if crop_h % height == 0 and crop_w % width == 0:
            return cv2.resize(view, (width, height), interpolation=cv2.INTER_AREA)
        view = cv2.GaussianBlur(view, (0, 0), ANTI_ALIAS_SIGMA * shrink)
    return cv2.resize(view, (width, height), interpolation=cv2.INTER_LINEAR)


def fit_crop(h: int, w: int, height: int, width: int) -> tuple[int, int, int, int]:
    """(top, left, crop height, crop width): the part of an h×w frame that `fit_frame` scales to
    `height`×`width` (the whole frame when it is that size already). What a consumer of the
    results needs to map the model's pixels back onto the camera's (`robotd.results.ros2`)."""
    if (h, w) == (height, width):
        return 0, 0, h, w
    rect_h, rect_w = fit_rect(h, w, height, width)
    crop_h, crop_w = max(1, round(rect_h)), max(1, round(rect_w))
    return (h - crop_h) // 2, (w - crop_w) // 2, crop_h, crop_w


def fit_rect(photo_h: int, photo_w: int, height: int, width: int) -> tuple[float, float]:
    """(h, w) of the largest rectangle of the frame's aspect that fits in the photograph."""
    aspect = width / height
    if photo_w / photo_h > aspect:
        return float(photo_h), photo_h * aspect
    return photo_w / aspect, float(photo_w)


class VideoSource(FrameSource):
    """A video file through OpenCV at the file's frame rate, looped at its end unless `loop` is
    False (then the end of the file is the end of the stream)."""

    def __init__(self, path: str | Path, *, loop: bool = True) -> None:
        self.path = Path(path)
        self.loop = loop
        if not self.path.is_file():
            raise SourceError(f"video file not found: {self.path}")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"cannot open video file {self.path} (not a video OpenCV can read)")
        ok, first = self._cap.read()
        if not ok or first is None:
            self._cap.release()
            raise SourceError(f"video file {self.path} has no readable frame")
        self._pending: np.ndarray | None = first
        self.frames_read = 0
        self._ended = False
        rate = float(self._cap.get(cv2.CAP_PROP_FPS))
        # Containers without a rate give 0 (or a clock's tick rate): such a file has no timeline.
        self.file_fps = rate if 0 < rate <= MAX_VIDEO_FPS else None
        shown = f"{self.file_fps:g} fps" if self.file_fps else "no frame rate"
        self.description = f"video {self.path} ({shown}{', looped' if loop else ''})"

    def next_offset_s(self) -> float | None:
        if self.file_fps is None or self._ended:
            return None
        # Continues across loops: the file stands for a camera that keeps its pace.
        return self.frames_read / self.file_fps

    def read(self) -> np.ndarray:
        if self._pending is not None:
            frame, self._pending = self._pending, None
        else:
            ok, frame = self._cap.read()
            if (not ok or frame is None) and self.loop:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                ok, frame = self._cap.read()
            if (not ok or frame is None) and not self.loop:
                self._ended = True
                raise EndOfStream(f"video file {self.path}: end of the file")
            if not ok or frame is None:
                raise SourceError(f"video file {self.path}: no more frames")
        self.frames_read += 1
        return _as_bgr(frame)

    def close(self) -> None:
        self._cap.release()


class CameraSource(FrameSource):
    """A camera by index through OpenCV; `device` (e.g. /dev/video0, the same camera as its
    index) is how the user named it, for messages."""

    def __init__(self, index: int, device: str | None = None) -> None:
        self.index = index
        name = device or str(index)
        self.description = f"camera {name}"
        _quiet_opencv()
        # By index, whichever way it was named: OpenCV maps index N to /dev/videoN (V4L2), and
        # an index is what every backend takes.
        self._cap = cv2.VideoCapture(index)
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"cannot open camera {name} (no such device, or it is busy)")

    def read(self) -> np.ndarray:
        for _ in range(CAMERA_READ_TRIES):
            ok, frame = self._cap.read()
            if ok and frame is not None:
                return _as_bgr(frame)
        raise SourceError(f"{self.description}: no frame after {CAMERA_READ_TRIES} tries")

    def close(self) -> None:
        self._cap.release()


def _as_bgr(frame: np.ndarray) -> np.ndarray:
    """OpenCV frames as uint8 H×W×3 (grey and BGRA converted)."""
    if frame.dtype != np.uint8:
        frame = cv2.convertScaleAbs(frame)
    if frame.ndim == 2:
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    if frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    return frame


def _check_size(height: int, width: int, *, kind: str = SYNTHETIC) -> None:
    for name, value in (("height", height), ("width", width)):
        if not 1 <= value <= MAX_SOURCE_SIDE_PX:
            raise SourceError(f"{kind} source: {name} must be 1..{MAX_SOURCE_SIDE_PX}")


def _quiet_opencv() -> None:
    """Keep OpenCV's own warnings (e.g. a missing /dev/video*) off the terminal: the SourceError
    says what went wrong in one line."""
    with contextlib.suppress(AttributeError):  # builds without the logging module
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
