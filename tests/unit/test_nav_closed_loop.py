"""The closed loop: a unicycle under the paper's limits, a textured world rendered in stereo,
zoo:stereo in onnxruntime and shared control. Full speed at a wall and into a box: without the
assistant the robot collides, with it the robot stops short, after driving most of the way."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nav.closed_loop import Maneuver, StereoPerception, run_maneuver
from nav.render import Pose, StereoRenderer
from nav.robot import UnicycleRobot
from nav.shared_control import AssistantParams, Command, Limit, RobotLimits
from nav.world import Face, World, corridor_with_wall

NORTH = math.pi / 2


def test_unicycle_respects_acceleration_limits_and_drives_arcs() -> None:
    robot = UnicycleRobot(Pose(0.0, 0.0, NORTH), RobotLimits())
    robot.step(Command(0.4, 0.0), 0.02)
    assert robot.v_mps == pytest.approx(0.16)  # a_max = 8 m/s² over 20 ms
    robot.step(Command(0.4, 0.0), 0.02)
    assert robot.v_mps == pytest.approx(0.32)
    robot.step(Command(9.0, 0.0), 0.02)
    assert robot.v_mps == pytest.approx(0.4)  # v_max
    robot.step(Command(0.0, 0.0), 0.02)
    assert robot.v_mps == pytest.approx(0.2)  # a_brake = 10 m/s²
    # a full circle at 0.4 m/s and 0.5 rad/s (radius 0.8 m) comes back to where it began
    robot = UnicycleRobot(Pose(1.0, 2.0, 0.3), RobotLimits(a_max_mps2=1e9))
    for _ in range(round(2 * math.pi / 0.5 / 0.01)):
        robot.step(Command(0.4, 0.5), 0.01)
    assert (robot.pose.x, robot.pose.y) == pytest.approx((1.0, 2.0), abs=2e-3)


def test_world_clearance_and_ray_casts() -> None:
    world = World(World.wall((-1.0, 2.0), (1.0, 2.0)) + World.box((3.0, 0.0), (1.0, 1.0)))
    assert world.clearance(0.0, 0.0) == pytest.approx(2.0)
    assert world.clearance(2.0, 0.0) == pytest.approx(0.5)  # the box's west side at x = 2.5
    depth, face, along, tall = world.cast(
        np.zeros(2), np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [1.0, 1.0]])
    )
    assert depth[:3].tolist() == [2.0, 2.5, math.inf]
    assert along[0] == pytest.approx(1.0) and tall[0] == world.faces[0].height_m
    assert depth[3] == math.inf  # through (2, 2): past the wall's end at x = 1, above the box
    assert isinstance(world.faces[int(face[1])], Face)


def test_rendered_pair_has_the_walls_disparity() -> None:
    """A wall 2 m ahead of the axle, so 1.9 m from the camera: d = fx·b/1.9 in the image centre."""
    from nav.camera import CameraModel
    from nav.disparity import DisparityRunner
    from nav.stereo_params import StereoParams

    camera = CameraModel.for_image(320, 240)
    left, right = StereoRenderer(camera, 320, 240).pair(corridor_with_wall(2.0), Pose(0, 0, NORTH))
    assert left.shape == (240, 320, 3) and left.dtype == np.uint8
    disparity = DisparityRunner(StereoParams(64))(left, right).disparity
    centre = disparity[90:110, 140:180]
    assert np.isfinite(centre).mean() > 0.95
    assert np.nanmedian(centre) == pytest.approx(camera.fx_px * camera.baseline_m / 1.9, abs=0.15)
    assert np.isnan(disparity[:20, 64:]).all()  # the sky above the wall: no chance matches


@pytest.mark.slow
@pytest.mark.parametrize(
    ("world", "maneuver"),
    [
        (
            corridor_with_wall(2.5),
            Maneuver("full speed at a wall", Pose(0, 0, NORTH), lambda t: Command(0.4, 0.0), 7.0),
        ),
        (
            World(corridor_with_wall(4.0).faces + World.box((-0.5, 1.8), (0.4, 0.4), 0.5)),
            Maneuver("curving into a box", Pose(0, 0, NORTH), lambda t: Command(0.4, 0.15), 6.0),
        ),
    ],
    ids=["wall", "box"],
)
def test_assistant_prevents_the_collision(world: World, maneuver: Maneuver) -> None:
    perception = StereoPerception(160, 120)
    # Stop with the camera beyond the nearest depth the disparity range sees (0.27 m here).
    params = AssistantParams(stop_margin_m=perception.camera.forward_m + 0.35)
    assert params.stop_margin_m - perception.camera.forward_m > perception.min_depth_m
    unassisted = run_maneuver(world, maneuver, None, params=params)
    assert unassisted.collided
    assisted = run_maneuver(world, maneuver, perception, params=params)
    assert not assisted.collided, assisted.min_clearance_m
    assert assisted.min_clearance_m > 0.1
    # it drove most of the way at full speed, and braked because of the obstacle
    assert assisted.distance_m > 0.8 * unassisted.distance_m - 0.5
    assert any(row.limit is Limit.OBSTACLE for row in assisted.trace)
    assert assisted.trace[-1].sent.v_mps < 0.05
    assert assisted.frames == round(maneuver.duration_s / 0.1)
