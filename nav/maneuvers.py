"""The circuit of the paper's test 2: seven approach maneuvers, the joystick pushed to full speed.

The paper drives an office circuit ten times with seven obstacle-approaching maneuvers per lap
(70 possible collisions). Here each maneuver is a small world of its own (walls and boxes of
:mod:`nav.world`) and a joystick script that, unassisted, ends in a collision: straight at walls
near and far, at an off-centre box and an oblique wall, curving left and right into boxes, and a
turn into a corridor wall. A lap gives every world fresh textures and the start pose a small,
seeded offset, so laps differ the way repeated drives of one circuit do.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from nav.closed_loop import Maneuver
from nav.render import Pose
from nav.shared_control import Command
from nav.world import Face, World, corridor_with_wall

MANEUVERS_PER_LAP = 7
FULL_SPEED_MPS = 0.4
"""The paper's v_max: the joystick is always at its extreme."""
NORTH_RAD = math.pi / 2
START_JITTER_M = 0.05
START_JITTER_RAD = 0.04
END_SLACK_S = 1.5
"""Each script runs this long past the time full speed would take to the obstacle."""


@dataclass(frozen=True)
class CircuitStep:
    """One maneuver of a lap: its world and its joystick script."""

    world: World
    maneuver: Maneuver


def _steady(v_mps: float, w_radps: float) -> Callable[[float], Command]:
    return lambda t: Command(v_mps, w_radps)


def _layouts() -> list[tuple[str, list[Face], float, float]]:
    """(name, faces, turn rate rad/s, distance to the obstacle m) of the seven maneuvers."""
    open_corridor = corridor_with_wall(6.0).faces
    return [
        ("straight at a wall 2.5 m ahead", corridor_with_wall(2.5).faces, 0.0, 2.3),
        ("straight at a wall 1.2 m ahead", corridor_with_wall(1.2).faces, 0.0, 1.0),
        (
            "straight at an off-centre box",
            open_corridor + World.box((0.15, 2.0), (0.5, 0.5), 0.5),
            0.0,
            1.6,
        ),
        (
            "curving left into a box",
            open_corridor + World.box((-0.5, 1.8), (0.4, 0.4), 0.5),
            0.15,
            1.5,
        ),
        (
            "curving right into a box",
            open_corridor + World.box((0.5, 1.8), (0.4, 0.4), 0.5),
            -0.15,
            1.5,
        ),
        (
            "straight at an oblique wall",
            World.wall((-1.5, 1.6), (1.5, 3.2)) + corridor_with_wall(6.0).faces[1:],
            0.0,
            2.2,
        ),
        ("turning into a corridor wall", corridor_with_wall(3.0).faces, 0.3, 2.0),
    ]


def circuit_lap(lap: int) -> list[CircuitStep]:
    """The seven maneuvers of lap `lap` (0-based): textures and start offsets seeded by it."""
    rng = np.random.default_rng(1000 + lap)
    steps = []
    for index, (name, faces, w_radps, distance_m) in enumerate(_layouts()):
        start = Pose(
            float(rng.uniform(-START_JITTER_M, START_JITTER_M)),
            float(rng.uniform(-START_JITTER_M, START_JITTER_M)),
            NORTH_RAD + float(rng.uniform(-START_JITTER_RAD, START_JITTER_RAD)),
        )
        world = World(faces, seed=lap * MANEUVERS_PER_LAP + index)
        duration_s = distance_m / FULL_SPEED_MPS + END_SLACK_S
        script = _steady(FULL_SPEED_MPS, w_radps)
        steps.append(CircuitStep(world, Maneuver(name, start, script, duration_s)))
    return steps
