"""Shared control against hand-computed limits: free paths, an obstacle ahead, the predictive
correction, left/right arcs, stale frames, deadline braking, what passes unchanged."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.errors import UserError
from nav.camera import CameraModel
from nav.closed_loop import DEFAULT_ROBOT_RADIUS_M
from nav.curvature import CurvatureBins, DcollProfile
from nav.live_drive import maneuver_params
from nav.shared_control import (
    AssistantParams,
    Command,
    Limit,
    RobotLimits,
    SharedControl,
)
from tests.helpers.nav import OFFCENTRE_640_FRAME34

A_MAX = 8.0  # the paper's a_max
CURVATURES = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])


def profile(*distances: float) -> DcollProfile:
    return DcollProfile(CURVATURES, np.array(distances, dtype=float))


def flat(distance: float) -> DcollProfile:
    return profile(*([distance] * len(CURVATURES)))


def control(**params: float) -> SharedControl:
    return SharedControl(RobotLimits(a_max_mps2=A_MAX), AssistantParams(**params))


def test_free_path_passes_the_joystick() -> None:
    sc = control()
    sc.observe(flat(5.0), t_frame=0.0)
    decision = sc.command(Command(0.4, 0.2), t_now=0.0)
    assert decision.command == Command(0.4, 0.2) and decision.limit is Limit.NONE
    assert decision.free_m == 5.0


def test_obstacle_ahead_limits_speed_on_the_same_curvature() -> None:
    sc = control()
    sc.observe(flat(0.005), t_frame=0.0)
    decision = sc.command(Command(0.4, 0.2), t_now=0.0)
    v = math.sqrt(2 * A_MAX * 0.005)  # 0.283 m/s
    assert decision.limit is Limit.OBSTACLE
    assert decision.command.v_mps == pytest.approx(v)
    assert decision.command.w_radps == pytest.approx(0.2 * v / 0.4)  # K = 0.5 kept


def test_predictive_correction_subtracts_the_distance_driven_since_the_frame() -> None:
    sc = control()
    sc.observe(flat(0.1), t_frame=10.0)
    # 0.2 s later at 0.4 m/s: 0.1 − 0.08 = 0.02 m left, sqrt(2·8·0.02) = 0.566 > 0.4: free
    assert sc.command(Command(0.4, 0.0), t_now=10.2).limit is Limit.NONE
    # 0.24 s later: 0.004 m left, 0.253 m/s
    late = sc.command(Command(0.4, 0.0), t_now=10.24)
    assert late.limit is Limit.OBSTACLE
    assert late.free_m == pytest.approx(0.004)
    assert late.command.v_mps == pytest.approx(math.sqrt(2 * A_MAX * 0.004))
    # past the obstacle by the estimate: stop
    assert sc.command(Command(0.4, 0.0), t_now=10.3).command.v_mps == 0.0


def test_left_obstacle_limits_left_turns_only() -> None:
    sc = control()
    sc.observe(profile(5.0, 5.0, 5.0, 0.001, 0.001), t_frame=0.0)  # obstacles at K ≥ 0.5
    left = sc.command(Command(0.2, 0.2), t_now=0.0)  # K = 1
    right = sc.command(Command(0.2, -0.2), t_now=0.0)  # K = −1
    assert left.limit is Limit.OBSTACLE and left.command.v_mps < 0.2
    assert right.limit is Limit.NONE and right.command == Command(0.2, -0.2)


def test_stop_margin_is_kept() -> None:
    sc = control(stop_margin_m=0.3)
    sc.observe(flat(0.3), t_frame=0.0)
    assert sc.command(Command(0.4, 0.0), t_now=0.0).command.v_mps == 0.0


def test_stale_frames_are_ignored() -> None:
    sc = control()
    assert sc.observe(flat(0.001), t_frame=2.0)
    assert not sc.observe(flat(5.0), t_frame=1.0)  # older: never applied out of order
    assert not sc.observe(flat(5.0), t_frame=2.0)
    assert sc.frame_time == 2.0
    assert sc.command(Command(0.4, 0.0), t_now=2.0).limit is Limit.OBSTACLE


def test_deadline_brakes_progressively_to_zero_then_fresh_frames_release() -> None:
    sc = control(deadline_s=1.0, deadline_decel_mps2=1.0)
    sc.observe(flat(5.0), t_frame=0.0)
    joystick = Command(0.4, 0.4)
    assert sc.command(joystick, t_now=0.5).command == joystick
    # the deadline passed at t = 1.0: the ramp starts from 0.4 m/s there, 1 m/s² down
    speeds = [sc.command(joystick, t_now=t).command for t in (1.1, 1.3, 1.45, 2.0)]
    assert [c.v_mps for c in speeds] == pytest.approx([0.3, 0.1, 0.0, 0.0], abs=1e-9)
    assert all(c.w_radps == pytest.approx(c.v_mps) for c in speeds)  # K = 1 kept
    assert sc.command(joystick, t_now=2.0).limit is Limit.DEADLINE
    sc.observe(flat(5.0), t_frame=2.0)
    assert sc.command(joystick, t_now=2.05).command == joystick


def test_no_information_yet_means_no_forward_motion() -> None:
    decision = control().command(Command(0.4, 0.0), t_now=0.0)
    assert decision.command.v_mps == 0.0 and decision.limit is Limit.DEADLINE


def test_reverse_and_turns_on_the_spot_pass() -> None:
    sc = control()
    sc.observe(flat(0.0), t_frame=0.0)
    for joystick in (Command(-0.2, 0.1), Command(0.0, 1.0)):
        assert sc.command(joystick, t_now=0.0).command == joystick


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_input_is_named(bad: float) -> None:
    with pytest.raises(UserError, match="must be finite"):
        control().command(Command(bad, 0.0), t_now=0.0)
    with pytest.raises(UserError, match="frame time"):
        control().observe(flat(1.0), t_frame=bad)


def test_the_circuits_assistant_stops_for_the_face_beside_an_empty_path_bin() -> None:
    # 640×480, straight at the off-centre box, 0.48 m from its face: the frame whose empty path
    # bin (nothing seen, 5 m) let the robot creep on until the face was nearer than the
    # disparity range sees, and hit it (docs/navigation.md, "Why the off-centre box was hit").
    camera = CameraModel.for_image(640, 480)
    params = maneuver_params(camera)
    assert params.half_width_m == DEFAULT_ROBOT_RADIUS_M
    frame = DcollProfile.from_bins(CurvatureBins(), np.array(OFFCENTRE_640_FRAME34))
    sc = SharedControl(RobotLimits(), params)
    sc.observe(frame, t_frame=0.0)
    decision = sc.command(Command(0.4, 0.0), t_now=0.1)
    # The bins beside the path see the face 0.40 m ahead: less than the stop margin, so stop.
    assert decision.limit is Limit.OBSTACLE
    assert decision.command == Command(0.0, 0.0)
    assert decision.free_m == pytest.approx(frame.within(0.0, 0.2) - 0.04 - params.stop_margin_m)
    # The paper's footprint (the axle's path alone) drives on at full speed.
    axle_only = SharedControl(RobotLimits(), replace(params, half_width_m=0.0))
    axle_only.observe(frame, t_frame=0.0)
    assert axle_only.command(Command(0.4, 0.0), t_now=0.1).command == Command(0.4, 0.0)


def test_bad_parameters_are_named() -> None:
    with pytest.raises(UserError, match="deadline_s"):
        AssistantParams(deadline_s=0.0)
    with pytest.raises(UserError, match="half_width_m"):
        AssistantParams(half_width_m=-0.1)
    with pytest.raises(UserError, match="a_max_mps2"):
        RobotLimits(a_max_mps2=-1.0)


@given(
    st.lists(st.floats(0.0, 5.0), min_size=5, max_size=5),
    st.floats(0.01, 0.4),
    st.floats(-1.0, 1.0),
    st.floats(0.0, 0.9),
)
def test_command_never_exceeds_the_joystick_or_the_stopping_speed(
    distances: list[float], v: float, w: float, age: float
) -> None:
    sc = control()
    sc.observe(profile(*distances), t_frame=0.0)
    decision = sc.command(Command(v, w), t_now=age)
    sent = decision.command
    free = profile(*distances).at(w / v) - v * age
    assert 0.0 <= sent.v_mps <= v
    assert sent.v_mps <= math.sqrt(2 * A_MAX * max(free, 0.0)) + 1e-12
    assert sent.w_radps * v == pytest.approx(w * sent.v_mps, abs=1e-12)
    assert (decision.limit is Limit.NONE) == (sent.v_mps == v)
