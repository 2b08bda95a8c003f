"""A scripted maneuver driven in wall-clock time, for a robot daemon that runs the stereo pipeline.

The in-process closed loop (:mod:`nav.closed_loop`) steps simulated time and draws each frame's
latency; here the latency is whatever the real runtime takes. A :class:`ManeuverDrive` holds
the maneuver's state (the unicycle, shared control, collisions and clearance) and is advanced to
clock times by its caller; a :class:`LiveDrive` advances it from a control thread of its own
every ``CONTROL_PERIOD_S`` of the clock, and is what a frame source uses
(`nav.stereo_sources`, ``stereo:maneuver:N``): the source renders each frame at
:meth:`LiveDrive.capture`'s pose and hands each d_coll the daemon computed to
:meth:`LiveDrive.observe` with the frame's capture time, so the assistant's correction
(``t_now − t_frame``) sees the real age.

- **Start.** The maneuver (its joystick script's time 0) starts when the first d_coll arrives:
  the robot's frame loop and its route are up and the assistant holds a frame, as a
  teleoperator starts driving once the assistant is on. Frames read before that show the start
  pose. The assistant off starts at the same point and ignores every d_coll.
- **Physics.** The robot keeps the last command until the next control step; when the control
  thread runs late (a robot short of CPU) the unicycle still moves for the time that passed,
  in sub-steps no longer than the control period, and each sub-step checks the clearance, so a
  late controller costs what it would cost a real robot. ``max_control_lag_s`` reports how late.
- **End.** At a collision (the robot's circle touches a face) or at the script's duration. The
  outcome (:class:`DriveOutcome`) goes to ``on_end`` once, from the control thread; a drive
  stopped before it ended (the daemon stopped) reports nothing.
"""

from __future__ import annotations

import json
import logging
import math
import os
import statistics
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from common.errors import UserError
from nav.camera import CameraModel
from nav.closed_loop import DEFAULT_CONTROL_PERIOD_S, DEFAULT_ROBOT_RADIUS_M, Maneuver
from nav.curvature import DcollProfile
from nav.render import Pose
from nav.robot import UnicycleRobot
from nav.shared_control import (
    DEFAULT_DEADLINE_S,
    AssistantParams,
    Command,
    RobotLimits,
    SharedControl,
)
from nav.world import World

log = logging.getLogger(__name__)

CONTROL_PERIOD_S = DEFAULT_CONTROL_PERIOD_S
STOP_MARGIN_BEYOND_CAMERA_M = 0.35
"""Free distance kept in front of the camera: beyond the nearest depth the disparity range sees
(0.27 m at any resolution), so a face the robot approaches never drops out of range (while the
bins within the half width see it: an empty path bin let the robot creep past the margin)."""
OUTCOME_FORMAT = 1
STOP_JOIN_S = 5.0
"""How long `LiveDrive.stop` waits for the control thread (it wakes every control period)."""

Clock = Callable[[], float]


def maneuver_params(camera: CameraModel, deadline_s: float = DEFAULT_DEADLINE_S) -> AssistantParams:
    """The assistant's parameters for the circuit: the stop margin keeps the camera
    `STOP_MARGIN_BEYOND_CAMERA_M` from a face (the in-process loop uses the same); the half
    width is the simulated robot's radius, so the bins beside the path count (an empty path bin
    near a face let the robot creep into the off-centre box at 640×480, docs/navigation.md);
    `deadline_s` is T_dead, the age past which d_coll is no longer trusted (the paper gives no
    value)."""
    return AssistantParams(
        deadline_s=deadline_s,
        stop_margin_m=camera.forward_m + STOP_MARGIN_BEYOND_CAMERA_M,
        half_width_m=DEFAULT_ROBOT_RADIUS_M,
    )


@dataclass(frozen=True)
class DriveOutcome:
    """How a maneuver ended. Times are seconds from the maneuver's start."""

    maneuver: str
    assisted: bool
    collided: bool
    collision_s: float | None
    min_clearance_m: float
    distance_m: float
    driven_s: float
    frames_read: int
    """Frames captured (rendered) for the daemon, before the start included."""
    frames_applied: int
    """d_coll values the assistant took (a result older than the one held is not applied)."""
    mean_dcoll_age_s: float | None
    """Mean age (now − capture time) of the d_coll held at each forward control step (the
    assistant's input, also when it brakes for the deadline); None: assistant off."""
    max_control_lag_s: float = 0.0
    """How late the control thread woke at worst (0 when stepped by hand)."""

    def to_json(self, **extra: Any) -> str:
        """One JSON line: the outcome's fields, `extra` (e.g. which maneuver of which lap)."""
        return json.dumps({"format": OUTCOME_FORMAT, **extra, **asdict(self)})


def write_outcome(path: Path, outcome: DriveOutcome, **extra: Any) -> None:
    """Write `outcome` as one JSON line to `path`, whole or not at all (a reader never sees a
    torn file): a temporary file beside it, then a rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(outcome.to_json(**extra) + "\n", encoding="utf-8")
    tmp.replace(path)


def read_outcome(path: Path) -> dict[str, Any]:
    """The outcome line `write_outcome` wrote (its fields and extras); a UserError naming the
    file when it is missing or not an outcome."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"no maneuver outcome at {path}: the maneuver did not end") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"maneuver outcome {path} is unreadable: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != OUTCOME_FORMAT:
        raise UserError(f"maneuver outcome {path}: expected format {OUTCOME_FORMAT}, got {data!r}")
    return data


class ManeuverDrive:
    """One maneuver's robot, assistant and bookkeeping, advanced to clock times by the caller.
    Not thread-safe (`LiveDrive` holds a lock around it); times are one clock's seconds."""

    def __init__(
        self,
        world: World,
        maneuver: Maneuver,
        *,
        assisted: bool,
        limits: RobotLimits | None = None,
        params: AssistantParams | None = None,
        robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M,
        control_period_s: float = CONTROL_PERIOD_S,
    ) -> None:
        if not (math.isfinite(control_period_s) and control_period_s > 0):
            raise UserError(f"control period must be a positive number, got {control_period_s}")
        self.world = world
        self.maneuver = maneuver
        self.assisted = assisted
        self.robot_radius_m = robot_radius_m
        self.control_period_s = control_period_s
        self.robot = UnicycleRobot(maneuver.start, limits or RobotLimits())
        self.control = SharedControl(limits, params)
        self.t0: float | None = None
        self.ended = False
        self.collision_s: float | None = None
        self.min_clearance_m = self._clearance(maneuver.start)
        self.distance_m = 0.0
        self.frames_read = 0
        self.frames_applied = 0
        self._t = 0.0  # the clock time the physics has reached
        self._sent = Command(0.0, 0.0)  # what the robot executes until the next control step
        self._ages: list[float] = []

    @property
    def started(self) -> bool:
        return self.t0 is not None

    @property
    def end_at(self) -> float:
        """The clock time the script runs out (inf before the start)."""
        return math.inf if self.t0 is None else self.t0 + self.maneuver.duration_s

    def capture(self, t: float) -> Pose | None:
        """The robot's pose at clock time `t` for a frame taken then (counted); None once the
        maneuver has ended."""
        pose = self.advance(t)
        if self.ended:
            return None
        self.frames_read += 1
        return pose

    def observe(self, profile: DcollProfile, t_frame: float, t_now: float) -> bool:
        """d_coll from the frame captured at `t_frame`, arriving at `t_now`: the first one starts
        the maneuver; the assistant takes it if it is on and newer than the one it holds."""
        if self.ended:
            return False
        if self.t0 is None:
            self.t0 = self._t = t_now
        if not self.assisted or not self.control.observe(profile, t_frame):
            return False
        self.frames_applied += 1
        return True

    def advance(self, t: float) -> Pose:
        """Move the robot under its last command up to clock time `t` (or the script's end), in
        sub-steps of at most the control period, checking the clearance after each."""
        if self.t0 is None or self.ended:
            return self.robot.pose
        until = min(t, self.end_at)
        span = until - self._t
        steps = math.ceil(span / self.control_period_s - 1e-9) if span > 0 else 0
        for _ in range(steps):
            before = self.robot.pose
            pose = self.robot.step(self._sent, span / steps)
            self._t += span / steps
            self.distance_m += math.dist((before.x, before.y), (pose.x, pose.y))
            clearance = self._clearance(pose)
            self.min_clearance_m = min(self.min_clearance_m, clearance)
            if clearance <= 0:
                self.ended = True
                self.collision_s = self._t - self.t0
                return pose
        if self._t >= self.end_at - 1e-9:
            self.ended = True
        return self.robot.pose

    def step_control(self, t: float) -> None:
        """A control step at clock time `t`: move the robot there, then send the joystick's
        command (through the assistant when it is on) until the next step."""
        self.advance(t)
        if self.t0 is None or self.ended:
            return
        joystick = self.maneuver.joystick(t - self.t0)
        if not self.assisted:
            self._sent = joystick
            return
        self._sent = self.control.command(joystick, t).command
        if joystick.v_mps > 0:  # a forward command is the one d_coll limits
            self._ages.append(t - self.control.frame_time)

    def outcome(self) -> DriveOutcome:
        """How the maneuver went so far (its end's, once `ended`)."""
        driven = 0.0 if self.t0 is None else self._t - self.t0
        return DriveOutcome(
            maneuver=self.maneuver.name,
            assisted=self.assisted,
            collided=self.collision_s is not None,
            collision_s=self.collision_s,
            min_clearance_m=self.min_clearance_m,
            distance_m=self.distance_m,
            driven_s=driven,
            frames_read=self.frames_read,
            frames_applied=self.frames_applied,
            mean_dcoll_age_s=statistics.fmean(self._ages) if self._ages else None,
        )

    def _clearance(self, pose: Pose) -> float:
        return self.world.clearance(pose.x, pose.y) - self.robot_radius_m


class LiveDrive:
    """A `ManeuverDrive` stepped every control period of `clock` by a thread of its own (started
    by the first d_coll); `capture` and `observe` may be called from any thread."""

    def __init__(
        self,
        drive: ManeuverDrive,
        on_end: Callable[[DriveOutcome], None],
        *,
        clock: Clock = time.monotonic,
    ) -> None:
        self.drive = drive
        self._on_end = on_end
        self._clock = clock
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.ended = threading.Event()
        """Set once the maneuver ended and its outcome was handed to `on_end`."""
        self._thread: threading.Thread | None = None
        self._lag_s = 0.0

    def capture(self) -> tuple[Pose, float] | None:
        """The robot's pose now and the clock time, for a frame taken now; None once the
        maneuver has ended (its source has no more frames)."""
        with self._lock:
            t = self._clock()
            pose = self.drive.capture(t)
            return None if pose is None else (pose, t)

    def observe(self, profile: DcollProfile, t_frame: float) -> bool:
        """A d_coll computed from the frame captured at `t_frame` (this clock); True when the
        assistant took it. The first one starts the maneuver and its control thread."""
        with self._lock:
            first = not self.drive.started
            applied = self.drive.observe(profile, t_frame, self._clock())
            if first and self.drive.started and not self._stop.is_set():
                self._thread = threading.Thread(
                    target=self._run, name="maneuver-control", daemon=True
                )
                self._thread.start()
        return applied

    def stop(self) -> None:
        """Stop the control thread (an unfinished maneuver reports no outcome)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(STOP_JOIN_S)

    def _run(self) -> None:
        period = self.drive.control_period_s
        with self._lock:
            t0 = self.drive.t0
            assert t0 is not None
            self.drive.step_control(t0)
        due = t0 + period
        while not self._stop.wait(max(0.0, due - self._clock())):
            now = self._clock()
            self._lag_s = max(self._lag_s, now - due)
            with self._lock:
                self.drive.step_control(now)
                if self.drive.ended:
                    break
            # On a fixed grid; ticks missed while descheduled are not replayed (the physics
            # has caught up with the time that passed).
            due += period
            if due <= now:
                due = now + period
        with self._lock:
            # Also when stopped: a frame's capture may have found the end just before the
            # source was closed, between two control steps.
            if not self.drive.ended:
                return
            outcome = replace(self.drive.outcome(), max_control_lag_s=self._lag_s)
        try:
            self._on_end(outcome)
        except Exception:  # a thread's exception would vanish: say what was lost
            log.exception("maneuver %r: could not report its outcome", self.drive.maneuver.name)
        finally:
            self.ended.set()
