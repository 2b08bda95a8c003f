"""`bench nav`'s Table V and Figs. 8-9: the paper's test 2 in the in-process closed loop.

The maneuvers (`nav.maneuvers`: 7 per lap) are driven in simulated time by `nav.closed_loop`
(rendered stereo pairs, zoo:stereo in onnxruntime, shared control, a unicycle with the paper's
limits). What an option changes is when d_coll reaches the assistant: each frame's latency is
drawn from the t_f samples MEASURED for that option and resolution on the daemons, and the robot
keeps one frame in flight, so the update rate follows those latencies too. The pipeline's output
is the same whichever option computes it (every cut and segment verifies with error 0), which is
why it runs here rather than on the daemons. "off" passes the joystick straight to the robot.
The assistant's T_dead is the bench's `--t-dead`: with latencies past it the assisted robot is
held at rest, so Table V needs it above them to say anything about collisions.
The maneuvers driven by the robot daemon itself, in real time, are `nav_live` (`--table5 live`);
Fig. 8 comes from here in both modes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nav.closed_loop import ManeuverResult, StereoPerception, run_maneuver
from nav.live_drive import maneuver_params
from nav.maneuvers import circuit_lap
from nav.render import Pose
from nav.shared_control import AssistantParams
from nav.world import corridor_with_wall

from .nav_rows import DEFAULT_T_DEAD_S, OFF, LoopFigures, Option, resolution_label

LOOP_THREADS = 2
"""onnxruntime threads of the closed loop's pipeline (the testbed is down by then)."""
WALL_AHEAD_M = 2.5
WALL_APPROACH_M = (0.0, 0.6, 1.2, 1.6)
"""Fig. 8: d_coll(K) seen from these distances driven toward a wall WALL_AHEAD_M ahead."""
NORTH_RAD = float(np.pi / 2)


@dataclass
class LoopResult:
    """Table V figures per (option, resolution label) and the data of Figs. 8-9."""

    figures: dict[tuple[Option, str], LoopFigures] = field(default_factory=dict)
    dcoll: list[dict[str, Any]] = field(default_factory=list)
    """Fig. 8: [{"ahead_m", "curvatures", "distances"}] at the largest resolution."""
    speeds: dict[str, Any] = field(default_factory=dict)
    """Fig. 9: {"option", "resolution", "t_s", "joystick_mps", "sent_mps"} over one lap."""
    maneuvers: dict[tuple[Option, str], list[dict[str, Any]]] = field(default_factory=dict)
    """Each maneuver's outcome per (option, resolution label) (`maneuver_outcome`)."""


def maneuver_outcome(lap: int, index: int, result: ManeuverResult) -> dict[str, Any]:
    """What `details` keeps of one maneuver driven in the loop (as `nav_live` keeps of a live
    one, where the loop has the figure)."""
    return {
        "lap": lap,
        "maneuver_index": index,
        "collided": result.collided,
        "collision_s": result.collision_s,
        "min_clearance_m": result.min_clearance_m,
        "distance_m": result.distance_m,
        "frames": result.frames,
    }


def drive_laps(
    perception: StereoPerception | None,
    params: AssistantParams,
    laps: int,
    latencies_s: Sequence[float] = (),
    seed: int = 0,
    on_lap: Callable[[int, list[Any]], None] | None = None,
) -> LoopFigures:
    """Drive `laps` laps; with `perception` each frame's latency is drawn from `latencies_s`."""
    rng = np.random.default_rng(seed)
    samples = np.asarray(latencies_s, dtype=np.float64)

    def draw() -> float:
        return float(rng.choice(samples))

    collisions = maneuvers = 0
    distance_m = 0.0
    clearances: list[float] = []
    for lap in range(laps):
        results = []
        for step in circuit_lap(lap):
            result = run_maneuver(
                step.world,
                step.maneuver,
                perception,
                params=params,
                frame_latency=draw if perception is not None else None,
            )
            collisions += int(result.collided)
            maneuvers += 1
            distance_m += result.distance_m
            if not result.collided:
                clearances.append(result.min_clearance_m)
            results.append(result)
        if on_lap is not None:
            on_lap(lap, results)
    return LoopFigures(
        collisions, maneuvers, distance_m / max(maneuvers, 1), min(clearances, default=None)
    )


def _collect(into: list[dict[str, Any]]) -> Callable[[int, list[Any]], None]:
    """An `on_lap` that appends each maneuver's outcome of the lap to `into`."""

    def on_lap(lap: int, results: list[Any]) -> None:
        into.extend(maneuver_outcome(lap, i, r) for i, r in enumerate(results))

    return on_lap


def _speed_trace(option: Option, label: str, results: list[Any]) -> dict[str, Any]:
    """One lap's joystick and commanded speeds, its maneuvers placed one after another."""
    t_s: list[float] = []
    joystick: list[float] = []
    sent: list[float] = []
    offset = 0.0
    for result in results:
        for row in result.trace:
            t_s.append(offset + row.t_s)
            joystick.append(row.joystick.v_mps)
            sent.append(row.sent.v_mps)
        offset = t_s[-1] if t_s else offset
    return {"option": option, "resolution": label, "t_s": t_s, "joystick_mps": joystick,
            "sent_mps": sent}  # fmt: skip


def wall_profiles(perception: StereoPerception) -> list[dict[str, Any]]:
    """Fig. 8's data: d_coll(K) at a few distances on the way to a wall."""
    world = corridor_with_wall(WALL_AHEAD_M)
    out = []
    for driven in WALL_APPROACH_M:
        profile = perception.profile(world, Pose(0.0, driven, NORTH_RAD))
        out.append(
            {
                "ahead_m": WALL_AHEAD_M - driven,
                "curvatures": profile.curvatures.tolist(),
                "distances": profile.distances.tolist(),
            }
        )
    return out


def fig8(size: tuple[int, int]) -> list[dict[str, Any]]:
    """Fig. 8's data at `size` (the wall approach, rendered and run in this process)."""
    return wall_profiles(StereoPerception(size[0], size[1], threads=LOOP_THREADS))


def table5(
    sizes: Sequence[tuple[int, int]],
    options: Sequence[Option],
    latencies: dict[tuple[Option, str], Sequence[float]],
    laps: int,
    log: Callable[[str], None] = lambda message: None,
    deadline_s: float = DEFAULT_T_DEAD_S,
) -> LoopResult:
    """Drive the circuit for each option in `options` (those with measured latencies, and
    "off") at each resolution, the assistant's T_dead `deadline_s`."""
    out = LoopResult()
    unassisted: tuple[LoopFigures, list[dict[str, Any]]] | None = None
    traces: dict[tuple[Option, str], dict[str, Any]] = {}
    for size in sizes:
        label = resolution_label(size)
        perception = StereoPerception(size[0], size[1], threads=LOOP_THREADS)
        params = maneuver_params(perception.camera, deadline_s)
        for option in options:
            if option == OFF:
                if unassisted is None:  # the camera plays no part: the same at any resolution
                    log(f"closed loop: assistant off, {laps} lap(s)")
                    outcomes: list[dict[str, Any]] = []
                    figures = drive_laps(None, params, laps, on_lap=_collect(outcomes))
                    unassisted = (figures, outcomes)
                out.figures[(OFF, label)], out.maneuvers[(OFF, label)] = unassisted
                continue
            samples = latencies.get((option, label), ())
            if not samples:
                continue
            log(f"closed loop: option {option} at {label}, {laps} lap(s), T_dead {deadline_s:g} s")
            outcomes = out.maneuvers.setdefault((option, label), [])
            collect = _collect(outcomes)

            def keep_first_lap(
                lap: int,
                results: list[Any],
                option: Option = option,
                label: str = label,
                collect: Callable[[int, list[Any]], None] = collect,
            ) -> None:
                collect(lap, results)
                if lap == 0:
                    traces[(option, label)] = _speed_trace(option, label, results)

            out.figures[(option, label)] = drive_laps(
                perception, params, laps, samples, seed=size[0], on_lap=keep_first_lap
            )
        if size == sizes[-1]:
            out.dcoll = wall_profiles(perception)
    if traces:
        # Fig. 9 shows option 1 (the paper's) at the largest resolution if it was driven.
        largest = resolution_label(sizes[-1])
        out.speeds = traces.get((1, largest)) or next(iter(traces.values()))
    return out
