"""`stereo:maneuver:N[:lap=L][:assist=off][:t_dead=S][:out=PATH]`: a maneuver of the navigation
circuit, driven live by the robot daemon's own results.

Maneuver N (0-6) of lap L (default 0) of the paper's test 2 (`nav.maneuvers.circuit_lap`: its
world, start pose and joystick script) runs in wall-clock time (`nav.live_drive.LiveDrive`: a
unicycle stepped by a control thread every 20 ms). Each `read()` renders the stereo pair at the
robot's pose at that instant (`nav.render.StereoRenderer`, RGB turned BGR like every source) and
notes the frame's capture time; each frame the daemon serves comes back through `on_result`,
and its `d_coll` output, with that capture time, reaches the assistant
(`nav.shared_control.SharedControl`), which filters the joystick (`assist=off`: the joystick
drives the robot directly, the results are ignored). The first result starts the maneuver.
`t_dead` is the assistant's T_dead in seconds (default 1): a d_coll older than that is no
longer trusted and the robot is braked to rest.

At a collision or at the script's end the maneuver is over: `read()` raises `EndOfStream`, so
the daemon finishes the frames in flight and stops, and the outcome (collision and when, minimum
clearance, distance, frames, mean age of d_coll at use; `nav.live_drive.DriveOutcome`) is
written to `out` as one JSON line with the maneuver's index and lap. A source closed before its
maneuver ended (a signal; the robot's calibration, which reads a second instance of its source
at start and never hands it results) writes nothing. Paths hold no colons.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np

from common.source_spec import SourceError, StereoManeuverSpec
from nav.camera import CameraModel
from nav.curvature import CurvatureBins, DcollProfile
from nav.live_drive import (
    Clock,
    DriveOutcome,
    LiveDrive,
    ManeuverDrive,
    maneuver_params,
    write_outcome,
)
from nav.maneuvers import MANEUVERS_PER_LAP, circuit_lap
from nav.render import StereoRenderer
from nav.shared_control import DEFAULT_DEADLINE_S
from nav.stereo_graph import Stage
from robotd.frame_path.frame import FrameResult
from robotd.sources.frame_sources import EndOfStream, FrameSource
from robotd.sources.stereo_frame import LEFT_VIEW, RIGHT_VIEW, STEREO_VIEWS, StereoFrame

log = logging.getLogger(__name__)

DCOLL_OUTPUT = Stage.DCOLL.value
"""zoo:stereo's output; its bins are the pipeline's defaults (`nav.curvature.CurvatureBins`)."""


class StereoManeuverSource(FrameSource):
    """Maneuver `maneuver` of lap `lap`, driven by the results the daemon hands back (see the
    module docstring)."""

    views = STEREO_VIEWS

    def __init__(
        self,
        height: int,
        width: int,
        *,
        maneuver: int,
        lap: int = 0,
        assist: bool = True,
        out: Path | None = None,
        seed: int = 0,
        clock: Clock = time.monotonic,
        deadline_s: float = DEFAULT_DEADLINE_S,
    ) -> None:
        if not 0 <= maneuver < MANEUVERS_PER_LAP:
            raise SourceError(
                f"stereo maneuver source: maneuver must be 0..{MANEUVERS_PER_LAP - 1}, "
                f"got {maneuver}"
            )
        if lap < 0:
            raise SourceError(f"stereo maneuver source: lap must be >= 0, got {lap}")
        if not (math.isfinite(deadline_s) and deadline_s > 0):
            raise SourceError(
                f"stereo maneuver source: t_dead must be a positive number of seconds, "
                f"got {deadline_s}"
            )
        if out is not None and not out.parent.is_dir():
            raise SourceError(f"stereo maneuver source: no directory {out.parent} for out={out}")
        step = circuit_lap(lap)[maneuver]
        camera = CameraModel.for_image(width, height)
        self.world = step.world
        self.index, self.lap, self.out = maneuver, lap, out
        self._bins = CurvatureBins()
        self._renderer = StereoRenderer(camera, width, height, seed)
        drive = ManeuverDrive(
            step.world,
            step.maneuver,
            assisted=assist,
            params=maneuver_params(camera, deadline_s),
        )
        self.drive = LiveDrive(drive, self._report, clock=clock)
        # Capture time (the drive's clock) of each frame read and not yet served, by frame index.
        self._captured: dict[int, float] = {}
        self._read = 0
        assistant = f"assistant on, T_dead {deadline_s:g} s" if assist else "assistant off"
        self.description = (
            f"stereo maneuver {maneuver} of lap {lap} ({step.maneuver.name}, {assistant}) "
            f"{width}x{height}"
        )

    def read(self) -> StereoFrame:
        captured = self.drive.capture()
        if captured is None:
            raise EndOfStream(f"{self.description}: the maneuver is over")
        pose, t = captured
        stamp = time.time()
        left, right = self._renderer.pair(self.world, pose)  # RGB, like the zoo's inputs
        # The daemon numbers frames in the order it reads them.
        self._captured[self._read] = t
        self._read += 1
        return StereoFrame(
            {
                LEFT_VIEW: cv2.cvtColor(left, cv2.COLOR_RGB2BGR),
                RIGHT_VIEW: cv2.cvtColor(right, cv2.COLOR_RGB2BGR),
            },
            stamp,
        )

    def on_result(self, result: FrameResult) -> None:
        t_frame = self._captured.pop(result.frame, None)
        if t_frame is None:
            return  # not a frame read from this source
        d_coll = result.outputs.get(DCOLL_OUTPUT)
        if d_coll is None:
            raise SourceError(
                f"{self.description}: the model has no {DCOLL_OUTPUT!r} output (it drives with "
                f"zoo:stereo's); outputs: {', '.join(sorted(result.outputs)) or 'none'}"
            )
        profile = DcollProfile.from_bins(self._bins, np.asarray(d_coll))
        self.drive.observe(profile, t_frame)

    def close(self) -> None:
        self.drive.stop()

    def _report(self, outcome: DriveOutcome) -> None:
        """The maneuver ended (the control thread): the outcome to `out`, a line to the log."""
        how = f"collision at {outcome.collision_s:.2f} s" if outcome.collided else "no collision"
        log.info(
            "%s: %s, min clearance %.3f m, %.2f m driven, %d frames applied",
            self.description,
            how,
            outcome.min_clearance_m,
            outcome.distance_m,
            outcome.frames_applied,
        )
        if self.out is not None:
            write_outcome(self.out, outcome, maneuver_index=self.index, lap=self.lap)


def open_maneuver_source(
    spec: StereoManeuverSpec, *, height: int, width: int, seed: int = 0
) -> StereoManeuverSource:
    """The source of a parsed `stereo:maneuver:...` spec."""
    return StereoManeuverSource(
        height,
        width,
        maneuver=spec.maneuver,
        lap=spec.lap,
        assist=spec.assist,
        out=spec.out,
        seed=seed,
        deadline_s=DEFAULT_DEADLINE_S if spec.t_dead_s is None else spec.t_dead_s,
    )
