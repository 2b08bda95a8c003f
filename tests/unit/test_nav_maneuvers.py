"""The test-2 circuit (`nav.maneuvers`) and the closed loop with measured latencies: every
maneuver ends in a collision without the assistant (the joystick at full speed), laps differ,
and a drawn latency keeps one frame in flight (camera ticks while busy are skipped)."""

from __future__ import annotations

import math

from nav.closed_loop import StereoPerception, run_maneuver
from nav.maneuvers import MANEUVERS_PER_LAP, circuit_lap
from nav.shared_control import AssistantParams

CONTROL_PERIOD_S = 0.02


def test_every_maneuver_collides_unassisted() -> None:
    lap = circuit_lap(0)
    assert len(lap) == MANEUVERS_PER_LAP
    for step in lap:
        result = run_maneuver(step.world, step.maneuver, None)
        assert result.collided, step.maneuver.name


def test_laps_differ_in_start_and_textures() -> None:
    first, second = circuit_lap(0), circuit_lap(1)
    assert first[0].maneuver.start != second[0].maneuver.start
    assert first[0].world.seed != second[0].world.seed
    assert [s.maneuver.name for s in first] == [s.maneuver.name for s in second]


def test_drawn_latency_keeps_one_frame_in_flight() -> None:
    """Regression guard: with a drawn latency the loop must not queue a frame per camera tick
    (that would update at the camera's rate whatever the measured latency)."""
    step = circuit_lap(0)[1]  # the short one: a wall 1.2 m ahead
    perception = StereoPerception(160, 120)
    params = AssistantParams(stop_margin_m=perception.camera.forward_m + 0.35)
    latency_s = 0.3
    result = run_maneuver(
        step.world, step.maneuver, perception, params=params, frame_latency=lambda: latency_s
    )
    steps = round(step.maneuver.duration_s / CONTROL_PERIOD_S)
    assert not result.collided
    # A frame every 15 steps: its result arrives on a camera tick, which takes the next one.
    assert result.frames == math.ceil(steps / round(latency_s / CONTROL_PERIOD_S))
    fixed = run_maneuver(step.world, step.maneuver, perception, params=params, latency_s=0.3)
    assert fixed.frames == math.ceil(steps / 5)  # fixed latency: a frame every camera tick
