"""`bench nav --table5 live`: Table V's maneuvers driven by the real robot daemon, in real time.

For each option and resolution every maneuver of every lap (`nav.maneuvers`: 7 a lap) is one run
of the robot daemon on the fleet `bench nav` launched for that resolution, on the testbed: the
robot host at `robot_cpu` of a core, its uplink shaped by `tc`, the camera at the paper's 10 fps
with one frame in flight, and the frame source `stereo:maneuver:N:lap=L:t_dead=S`
(`nav.maneuver_source`; S is `--t-dead`, the assistant's T_dead): each frame is rendered at
the robot's pose when it is taken, the d_coll the runtime computes for it (where the option says,
over Zenoh) reaches the assistant with the frame's capture time, a control thread on the robot
steps the unicycle every 20 ms, and the run ends with the maneuver. The outcome file (collision,
minimum clearance, distance, frames applied, mean age of d_coll at use, the control thread's
worst lag) is read back from the run's folder (the testbed's hosts share the filesystem). "off"
runs the daemon as option 1 and ignores its results: the joystick drives the robot. A frame read
without a telemetry record is lost.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import UserError
from common.source_spec import STEREO_MANEUVER, STEREO_PREFIX
from nav.closed_loop import DEFAULT_FRAME_PERIOD_S
from nav.live_drive import read_outcome
from nav.maneuvers import MANEUVERS_PER_LAP, circuit_lap

from .nav_rows import (
    DEFAULT_T_DEAD_S,
    OFF,
    LoopFigures,
    Option,
    resolution_label,
    robot_policy,
)
from .runner import TestbedFleet
from .stats import by_frame, lost_frames

LIVE_FPS = 1.0 / DEFAULT_FRAME_PERIOD_S
"""The paper's test 2 camera (10 fps), as the in-process loop's."""
OFF_POLICY = "option:1"
"""What the daemon runs while the assistant is off (its d_coll is not used)."""
FRAME_BOUND = 100_000
"""The robot's --frames: far beyond any maneuver, which ends the run itself."""
RUN_SLACK_S = 180.0
"""A run's bound beyond its maneuver: the robot's start-up and its first frame's result."""
DETAIL_KEYS = (
    "lap",
    "maneuver_index",
    "collided",
    "collision_s",
    "min_clearance_m",
    "distance_m",
    "frames_read",
    "frames_applied",
    "mean_dcoll_age_s",
    "max_control_lag_s",
)
"""What `details` keeps of each maneuver's outcome."""


@dataclass
class LiveRuns:
    """Table V of one option at one resolution from its robot runs."""

    figures: LoopFigures
    maneuvers: list[dict[str, Any]] = field(default_factory=list)
    """Each maneuver's outcome (`DETAIL_KEYS`)."""
    lost: int = 0


def maneuver_spec(
    index: int, lap: int, assist: bool, out: Path, t_dead_s: float = DEFAULT_T_DEAD_S
) -> str:
    """The robot's `--source` for maneuver `index` of `lap` with the assistant's T_dead
    `t_dead_s`, writing its outcome to `out`."""
    if ":" in str(out):
        raise UserError(f"--workdir: the maneuver outcome path {out} must not contain ':'")
    state = "on" if assist else "off"
    # repr: the shortest text that reads back as the same float.
    return (
        f"{STEREO_PREFIX}{STEREO_MANEUVER}:{index}:lap={lap}:assist={state}"
        f":t_dead={float(t_dead_s)!r}:out={out}"
    )


def figures(outcomes: Sequence[dict[str, Any]]) -> LoopFigures:
    """Collisions over maneuvers, mean distance, smallest clearance without a collision."""
    clear = [float(o["min_clearance_m"]) for o in outcomes if not o["collided"]]
    distance = sum(float(o["distance_m"]) for o in outcomes)
    return LoopFigures(
        collisions=sum(1 for o in outcomes if o["collided"]),
        maneuvers=len(outcomes),
        distance_m=distance / max(len(outcomes), 1),
        min_clearance_m=min(clear, default=None),
    )


def drive(
    tf: TestbedFleet,
    option: Option,
    size: tuple[int, int],
    laps: int,
    robot_cpu: float,
    log: Callable[[str], None] = lambda message: None,
    t_dead_s: float = DEFAULT_T_DEAD_S,
) -> LiveRuns:
    """Drive `laps` laps of the circuit with `option` on the fleet `tf` launched for `size`,
    the assistant's T_dead `t_dead_s`."""
    assert tf.config is not None, "launch the fleet first"
    label = resolution_label(size)
    folder = tf.config.parent / "maneuvers"
    folder.mkdir(parents=True, exist_ok=True)
    policy = OFF_POLICY if option == OFF else robot_policy(option)
    outcomes: list[dict[str, Any]] = []
    lost = 0
    for lap in range(laps):
        for step_index, step in enumerate(circuit_lap(lap)):
            out = folder / f"{option}-{label}-lap{lap}-{step_index}.json"
            out.unlink(missing_ok=True)
            spec = maneuver_spec(step_index, lap, option != OFF, out, t_dead_s)
            log(f"{label}, option {option}: lap {lap}, maneuver {step_index}: {step.maneuver.name}")
            tf.start_robot(
                policy,
                frames=FRAME_BOUND,
                fps=LIVE_FPS,
                cpu_fraction=robot_cpu,
                extra=["--source", spec],
                tag=f"{option}-m{step_index}",
            )
            records = by_frame(tf.finish_robot(RUN_SLACK_S + step.maneuver.duration_s))
            outcome = read_outcome(out)
            lost += len(lost_frames(records, int(outcome["frames_read"])))
            outcomes.append({key: outcome.get(key) for key in DETAIL_KEYS})
    assert len(outcomes) == laps * MANEUVERS_PER_LAP
    return LiveRuns(figures(outcomes), outcomes, lost)
