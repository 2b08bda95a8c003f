"""A scripted joystick maneuver in closed loop: robot, camera, stereo pipeline, shared control.

Simulated time in fixed control steps (the robot's actuation period). Every ``frame_period_s``
the camera renders a stereo pair at the robot's pose (:mod:`nav.render`); zoo:stereo's graph,
run by onnxruntime in this process, turns it into d_coll, which reaches the assistant
``latency_s`` after the frame was taken (the paper's t_o + t_p + t_c + t_f, a parameter here, so
a run is deterministic whatever this host's speed). Each step the joystick's command goes through
:class:`nav.shared_control.SharedControl` (or straight to the robot, unassisted). The robot's
footprint is a circle around the axle centre; touching a face is a collision and ends the run.

With ``frame_latency`` (a draw per frame, e.g. from latencies measured on the daemons) the robot
keeps one frame in flight, as a robot that works at full speed does: a camera tick while a frame
is still being processed is skipped, so the update rate follows the drawn latencies.

The stop margin must keep the camera beyond the nearest depth the disparity range covers: a
face nearer than that is not seen at all (its disparity is out of range), so a robot allowed that
close would drive on.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import onnxruntime as ort

from common.errors import UserError
from nav.camera import CameraModel
from nav.curvature import DcollProfile
from nav.render import Pose, StereoRenderer
from nav.robot import UnicycleRobot
from nav.shared_control import AssistantParams, Command, Limit, RobotLimits, SharedControl
from nav.stereo_graph import LEFT_INPUT, RIGHT_INPUT, StereoPipeline, build_model
from nav.stereo_params import StereoParams, zoo_disparities
from nav.world import World

DEFAULT_ROBOT_RADIUS_M = 0.2
DEFAULT_CONTROL_PERIOD_S = 0.02
# The paper's test 2 runs the camera at 10 fps.
DEFAULT_FRAME_PERIOD_S = 0.1
DEFAULT_LATENCY_S = 0.1


@dataclass(frozen=True)
class Maneuver:
    """A start pose and a joystick script (command as a function of time)."""

    name: str
    start: Pose
    joystick: Callable[[float], Command]
    duration_s: float


@dataclass(frozen=True)
class TraceRow:
    t_s: float
    joystick: Command
    sent: Command
    limit: Limit
    pose: Pose


@dataclass
class ManeuverResult:
    name: str
    assisted: bool
    collided: bool = False
    collision_s: float | None = None
    min_clearance_m: float = math.inf
    distance_m: float = 0.0
    frames: int = 0
    trace: list[TraceRow] = field(default_factory=list)


class StereoPerception:
    """The camera and the whole stereo pipeline (zoo:stereo's graph) for one image size."""

    def __init__(self, width: int, height: int, threads: int = 1, seed: int = 0) -> None:
        self.camera = CameraModel.for_image(width, height)
        self.pipeline = StereoPipeline(StereoParams(zoo_disparities(width)), self.camera)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.log_severity_level = 3
        model = build_model(self.pipeline, height=height, width=width)
        self.session = ort.InferenceSession(
            model.SerializeToString(), options, providers=["CPUExecutionProvider"]
        )
        self.renderer = StereoRenderer(self.camera, width, height, seed)

    @property
    def min_depth_m(self) -> float:
        """The nearest depth the disparity range sees (at disparity D − 1)."""
        return self.camera.depth_m(self.pipeline.params.max_disparity - 1)

    def profile(self, world: World, pose: Pose) -> DcollProfile:
        left, right = self.renderer.pair(world, pose)
        (d_coll,) = self.session.run(None, {LEFT_INPUT: left[None], RIGHT_INPUT: right[None]})
        return DcollProfile.from_bins(self.pipeline.bins, np.asarray(d_coll)[0])


def run_maneuver(
    world: World,
    maneuver: Maneuver,
    perception: StereoPerception | None,
    limits: RobotLimits | None = None,
    params: AssistantParams | None = None,
    *,
    robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M,
    control_period_s: float = DEFAULT_CONTROL_PERIOD_S,
    frame_period_s: float = DEFAULT_FRAME_PERIOD_S,
    latency_s: float = DEFAULT_LATENCY_S,
    frame_latency: Callable[[], float] | None = None,
) -> ManeuverResult:
    """Drive ``maneuver`` in ``world``; with ``perception`` the assistant filters the joystick,
    without it the joystick drives the robot directly. ``frame_latency``: each frame's latency
    drawn from it instead of ``latency_s``, one frame in flight at a time."""
    limits = limits or RobotLimits()
    frame_steps = round(frame_period_s / control_period_s)
    latency_steps = round(latency_s / control_period_s)
    if frame_steps < 1 or latency_steps < 0 or control_period_s <= 0:
        raise UserError(
            f"periods must be positive multiples of the control period {control_period_s} s"
        )
    robot = UnicycleRobot(maneuver.start, limits)
    control = SharedControl(limits, params)
    result = ManeuverResult(maneuver.name, assisted=perception is not None)
    in_flight: deque[tuple[int, float, DcollProfile]] = deque()
    steps = round(maneuver.duration_s / control_period_s)
    for step in range(steps):
        t = step * control_period_s
        if perception is not None:
            # A frame whose result arrives at this step frees the robot for this tick.
            busy = frame_latency is not None and bool(in_flight) and in_flight[0][0] > step
            if step % frame_steps == 0 and not busy:
                delay = latency_steps
                if frame_latency is not None:
                    delay = max(1, round(frame_latency() / control_period_s))
                in_flight.append((step + delay, t, perception.profile(world, robot.pose)))
                result.frames += 1
            while in_flight and in_flight[0][0] <= step:
                _, t_frame, profile = in_flight.popleft()
                control.observe(profile, t_frame)
        joystick = maneuver.joystick(t)
        if perception is not None:
            decision = control.command(joystick, t)
            sent, limit = decision.command, decision.limit
        else:
            sent, limit = joystick, Limit.NONE
        before = robot.pose
        pose = robot.step(sent, control_period_s)
        result.distance_m += math.dist((before.x, before.y), (pose.x, pose.y))
        result.trace.append(TraceRow(t, joystick, sent, limit, pose))
        clearance = world.clearance(pose.x, pose.y) - robot_radius_m
        result.min_clearance_m = min(result.min_clearance_m, clearance)
        if clearance <= 0:
            result.collided = True
            result.collision_s = t + control_period_s
            break
    return result
