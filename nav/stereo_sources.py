"""Stereo frame sources of the robot daemon: two views a frame, for models with two image inputs.

Each frame is a `robotd.sources.stereo_frame.StereoFrame`: the views `left` and `right` (uint8 BGR,
H×W×3 each, the model's input size), rectified (the same rows show the same scene lines), and
the wall clock when the pair was taken.

- `stereo:world[,speed=F]`: pairs rendered by `nav.render.StereoRenderer` (the closed-loop
  simulation's camera, `nav.camera.CameraModel.for_image` at the frame size) from a robot driving
  a loop of radius `LOOP_RADIUS_M` in a walled room with four boxes (`loop_world`): textured
  faces at 1–4 m, so d_coll changes as the robot goes round. The path is bounded (the robot
  never leaves the loop, never touches a face) and seeded: the seed draws the textures, the
  sensor noise and where on the loop the robot starts; frame n is where the robot is after n
  frame periods of `WORLD_FRAME_PERIOD_S` (the paper's 10 fps) at `speed` m/s (default 0.3; 0
  is a robot standing still).
- `stereo:motorcycle[,motion=M][,speed=F]`: Middlebury 2014's Motorcycle pair, which scikit-image
  ships (`nav.stereo_eval.stereo_motorcycle`, nothing is downloaded).
- `stereo:LEFT,RIGHT[,motion=M][,speed=F]`: two image files of one size (paths without commas),
  e.g. a pair saved from a stereo camera.
- `stereo:maneuver:N[:lap=L][:assist=off][:t_dead=S][:out=PATH]`: maneuver N of the navigation
  circuit, driven live by the daemon's own d_coll results until it ends (`nav.maneuver_source`).

A pair is repeated: without `motion` or `speed` each frame is the whole pair resized to the
frame size; with them both views move through the `photo` source's virtual camera
(`robotd.sources.frame_sources.CameraPath`: pan, zoom, shake), the same warp for both, so the pair
stays rectified. The specs are parsed by `common.source_spec`; a source that cannot be opened is a
`SourceError` naming it.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common.source_spec import (
    STEREO_MOTORCYCLE,
    CameraMotion,
    SourceError,
    StereoManeuverSpec,
    StereoPairSpec,
    StereoWorldSpec,
)
from nav.camera import CameraModel
from nav.maneuver_source import open_maneuver_source
from nav.render import Pose, StereoRenderer
from nav.world import World
from robotd.sources.frame_sources import (
    MAX_PHOTO_SPEED,
    CameraPath,
    FrameSource,
    fit_photo,
    warp_view,
)
from robotd.sources.stereo_frame import LEFT_VIEW, RIGHT_VIEW, STEREO_VIEWS, StereoFrame

# The world's room (walls at ±ROOM_HALF_M) and its boxes, centred BOX_OFFSET_M from the room's
# centre on both axes: outside the loop, in view ahead as the robot goes round.
ROOM_HALF_M = 2.5
BOX_OFFSET_M = 1.9
BOX_SIDE_M = 0.5
LOOP_RADIUS_M = 1.2
# The heading sways about the loop's tangent (this amplitude, this many times a lap), so the
# camera also sees the boxes and corners off the tangent.
HEADING_SWAY_RAD = 0.2
SWAYS_PER_LAP = 3
WORLD_FRAME_PERIOD_S = 0.1
DEFAULT_WORLD_SPEED_MPS = 0.3
MAX_WORLD_SPEED_MPS = 2.0


def loop_world(seed: int = 0) -> World:
    """The room of `stereo:world`: four walls and four boxes, textures drawn from `seed`."""
    h = ROOM_HALF_M
    faces = (
        World.wall((-h, -h), (h, -h))
        + World.wall((h, -h), (h, h))
        + World.wall((h, h), (-h, h))
        + World.wall((-h, h), (-h, -h))
    )
    for sx in (-1, 1):
        for sy in (-1, 1):
            faces += World.box((sx * BOX_OFFSET_M, sy * BOX_OFFSET_M), (BOX_SIDE_M, BOX_SIDE_M))
    return World(faces, seed=seed)


class StereoWorldSource(FrameSource):
    """Pairs rendered from a robot driving a loop in `loop_world` (see the module docstring)."""

    views = STEREO_VIEWS

    def __init__(
        self, height: int, width: int, *, seed: int = 0, speed: float = DEFAULT_WORLD_SPEED_MPS
    ) -> None:
        if not 0.0 <= speed <= MAX_WORLD_SPEED_MPS or not math.isfinite(speed):
            raise SourceError(
                f"stereo world source: speed must be in [0, {MAX_WORLD_SPEED_MPS:g}] m/s, "
                f"got {speed}"
            )
        if seed < 0:
            raise SourceError(f"stereo world source: seed must be >= 0, got {seed}")
        self.height, self.width, self.speed = height, width, speed
        self.world = loop_world(seed)
        self.camera = CameraModel.for_image(width, height)
        self._renderer = StereoRenderer(self.camera, width, height, seed)
        self._start_rad = float(np.random.default_rng(seed).uniform(0.0, 2 * math.pi))
        self.index = 0
        self.description = f"stereo world {width}x{height} (seed {seed}, speed {speed:g} m/s)"

    def pose_at(self, n: int) -> Pose:
        """Where the robot is at frame `n`: on the loop, heading along it (counter-clockwise)
        with a small sway."""
        phi = self._start_rad + self.speed * n * WORLD_FRAME_PERIOD_S / LOOP_RADIUS_M
        sway = HEADING_SWAY_RAD * math.sin(SWAYS_PER_LAP * (phi - self._start_rad))
        return Pose(
            LOOP_RADIUS_M * math.cos(phi), LOOP_RADIUS_M * math.sin(phi), phi + math.pi / 2 + sway
        )

    def read(self) -> StereoFrame:
        pose = self.pose_at(self.index)
        self.index += 1
        stamp = time.time()
        left, right = self._renderer.pair(self.world, pose)  # RGB, like the zoo's inputs
        return StereoFrame(
            {
                LEFT_VIEW: cv2.cvtColor(left, cv2.COLOR_RGB2BGR),
                RIGHT_VIEW: cv2.cvtColor(right, cv2.COLOR_RGB2BGR),
            },
            stamp,
        )


class StereoPairSource(FrameSource):
    """One rectified pair (uint8 BGR, one size) repeated, still or through a moving virtual
    camera that warps both views alike (see the module docstring)."""

    views = STEREO_VIEWS

    def __init__(
        self,
        left: np.ndarray,
        right: np.ndarray,
        height: int,
        width: int,
        *,
        name: str,
        seed: int = 0,
        motion: CameraMotion | None = None,
        speed: float | None = None,
    ) -> None:
        if left.shape != right.shape or left.ndim != 3 or left.shape[2] != 3:
            raise SourceError(
                f"stereo source {name}: the views must be colour images of one size, got "
                f"{_size(left)} and {_size(right)}"
            )
        if speed is not None and (not 0.0 <= speed <= MAX_PHOTO_SPEED or not math.isfinite(speed)):
            raise SourceError(
                f"stereo source {name}: speed must be in [0, {MAX_PHOTO_SPEED:g}], got {speed}"
            )
        self.height, self.width = height, width
        self.index = 0
        self.moving = motion is not None or speed is not None
        self.motion = motion or CameraMotion.MIXED
        self.speed = 1.0 if speed is None else speed
        if self.moving:
            self._pair = (fit_photo(left, height, width), fit_photo(right, height, width))
            # One stream of the seed's, as the photo source's first scene.
            stream = np.random.SeedSequence(seed, spawn_key=(0,))
            self._path = CameraPath(np.random.default_rng(stream))
            how = f"motion={self.motion.value}, speed={self.speed:g}, seed {seed}"
        else:
            self._pair = (_resized(left, height, width), _resized(right, height, width))
            how = "still"
        self.description = f"stereo {name} {width}x{height} ({how})"

    def read(self) -> StereoFrame:
        n = self.index
        self.index += 1
        stamp = time.time()
        left, right = self._pair
        if self.moving:
            h, w = self.height, self.width
            ph, pw = left.shape[:2]
            matrix = self._path.view(n * self.speed, self.motion, ph, pw, h, w)
            left, right = warp_view(left, matrix, h, w), warp_view(right, matrix, h, w)
        return StereoFrame({LEFT_VIEW: left, RIGHT_VIEW: right}, stamp)


def open_stereo_source(
    spec: StereoWorldSpec | StereoPairSpec | StereoManeuverSpec,
    *,
    height: int,
    width: int,
    seed: int = 0,
) -> FrameSource:
    """The stereo source of a parsed `stereo:...` spec (see the module docstring)."""
    if isinstance(spec, StereoManeuverSpec):
        return open_maneuver_source(spec, height=height, width=width, seed=seed)
    if isinstance(spec, StereoWorldSpec):
        return StereoWorldSource(height, width, seed=seed, **_given(speed=spec.speed))
    options = _given(motion=spec.motion, speed=spec.speed)
    if spec.paths is None:
        # Imported here: scikit-image is slow to import and only this pair needs it.
        from nav.stereo_eval import stereo_motorcycle

        left_rgb, right_rgb, _ = stereo_motorcycle()
        left, right = (cv2.cvtColor(v, cv2.COLOR_RGB2BGR) for v in (left_rgb, right_rgb))
        return StereoPairSource(
            left, right, height, width, name=STEREO_MOTORCYCLE, seed=seed, **options
        )
    paths = spec.paths
    left, right = (_read_image(spec.text, p) for p in paths)
    if left.shape != right.shape:
        raise SourceError(
            f"source {spec.text!r}: {paths[0]} is {_size(left)} and {paths[1]} is {_size(right)}; "
            "the views of a pair must be one size"
        )
    name = f"{paths[0].name} + {paths[1].name}"
    return StereoPairSource(left, right, height, width, name=name, seed=seed, **options)


def _given(**options: Any) -> dict[str, Any]:
    """The options a spec set (None: the source's own default)."""
    return {name: value for name, value in options.items() if value is not None}


def _read_image(spec: str, path: Path) -> np.ndarray:
    if not path.is_file():
        raise SourceError(f"source {spec!r}: image file not found: {path}")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise SourceError(f"source {spec!r}: cannot read {path} (not an image OpenCV can read)")
    return image


def _resized(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """The whole image at `height`×`width` (area interpolation when shrinking), read-only."""
    if image.shape[:2] != (height, width):
        shrink = image.shape[0] > height or image.shape[1] > width
        interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        image = cv2.resize(image, (width, height), interpolation=interpolation)
    image = np.ascontiguousarray(image)
    image.setflags(write=False)
    return image


def _size(image: np.ndarray) -> str:
    """`W×H` of an image (with its channels when not 3)."""
    shape = image.shape
    channels = "" if image.ndim == 3 and shape[2] == 3 else f", shape {list(shape)}"
    return f"{shape[1]}x{shape[0]}{channels}" if image.ndim >= 2 else f"shape {list(shape)}"
