"""`bench nav`'s options and result rows: what the robot's telemetry says of one option.

The paper's Table III is the update frequency (frames per second the robot completes, working
as fast as it can), its Table IV the delays: t_o the offload (the network's share of the round
trip, `transfer_s`), t_p the cloud's processing (`cloud_s`: its queue and compute), t_c the
robot's own compute (`prefix_s` + `suffix_local_s`: the stages before the cut and the tail after
it) and t_f the whole frame (`latency_s`, capture to d_coll). Table V's collisions come from the
closed loop (`nav_loop`, simulated time) or from the maneuvers driven by the robot daemon
(`nav_live`). A row of the JSON contract joins them per option and resolution.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from common.errors import UserError
from nav.shared_control import DEFAULT_DEADLINE_S

from .stats import Record

ROW_KEYS = (
    "option",
    "resolution",
    "update_hz",
    "t_o_s",
    "t_p_s",
    "t_c_s",
    "t_f_s",
    "collisions",
    "maneuvers",
    "lost",
)
"""The JSON contract's keys of a result row, in order."""
OFF = "off"
"""The assistant off: the joystick passed straight to the robot (closed loop only)."""
ELASTIC = "elastic"
"""The runtime's learner over whole suffixes (options 1, 2 and 4 among them)."""
ELASTIC_SEGMENTS = "elastic-segments"
"""The learner with the split's segments among its actions too (option 3 among them): what the
runtime's `elastic` does on a split made with `cuts.segments`."""
ELASTIC_SUFFIXES_POLICY = "elastic-suffixes"
"""The bench's policy variant (`fleet.POLICY_VARIANTS`) that runs the `elastic` row."""
NAV_OPTIONS: tuple[int | str, ...] = (1, 2, 3, 4, ELASTIC, ELASTIC_SEGMENTS, OFF)
TABLE5_SIM = "sim"
"""Table V in the in-process closed loop, latencies drawn from the measured t_f."""
TABLE5_LIVE = "live"
"""Table V driven by the robot daemon on the testbed, one run per maneuver, in real time."""
TABLE5_MODES = (TABLE5_SIM, TABLE5_LIVE)
DEFAULT_T_DEAD_S = DEFAULT_DEADLINE_S
"""`--t-dead`'s default: the assistant's own T_dead (the paper gives none)."""
MIN_SIZE_PX = (64, 48)
MAX_SIZE_PX = (1920, 1080)

Option = int | str


def parse_options(text: str) -> list[Option]:
    """'1,4,off' -> [1, 4, 'off']; anything else than 1-4, elastic, elastic-segments or off is
    one line."""
    found: list[Option] = []
    for part in (p.strip().lower() for p in text.split(",")):
        if not part:
            continue
        option: Option = int(part) if part.isdigit() else part
        if option not in NAV_OPTIONS:
            known = ", ".join(map(str, NAV_OPTIONS))
            raise UserError(f"--options: unknown {part!r}; expected some of {known}")
        if option not in found:
            found.append(option)
    if not found:
        known = ", ".join(map(str, NAV_OPTIONS))
        raise UserError(f"--options: expected at least one of {known}")
    return found


def parse_table5(text: str) -> str:
    """`--table5`: 'sim' or 'live' (any case); anything else is one line."""
    mode = text.strip().lower()
    if mode not in TABLE5_MODES:
        raise UserError(f"--table5: expected {' or '.join(TABLE5_MODES)}, got {text!r}")
    return mode


def check_t_dead(seconds: float) -> float:
    """`--t-dead`: the assistant's T_dead in seconds, positive and finite; else one line."""
    if not (math.isfinite(seconds) and seconds > 0):
        raise UserError(f"--t-dead {seconds:g}: must be a positive number of seconds")
    return seconds


def parse_resolution(text: str, option: str = "--resolution") -> tuple[int, int]:
    """'320x240' -> (320, 240) as (width, height); errors name `option`."""
    width_text, _, height_text = text.strip().lower().partition("x")
    if not (width_text.isdigit() and height_text.isdigit()):
        raise UserError(f"{option}: {text.strip()!r} is not WIDTHxHEIGHT (e.g. 640x480)")
    size = (int(width_text), int(height_text))
    if not all(lo <= v <= hi for v, lo, hi in zip(size, MIN_SIZE_PX, MAX_SIZE_PX, strict=True)):
        raise UserError(
            f"{option}: {text.strip()} is outside {MIN_SIZE_PX[0]}x{MIN_SIZE_PX[1]} to "
            f"{MAX_SIZE_PX[0]}x{MAX_SIZE_PX[1]}"
        )
    return size


def parse_resolutions(text: str) -> list[tuple[int, int]]:
    """'320x240,640x480' -> [(320, 240), (640, 480)] as (width, height)."""
    found: list[tuple[int, int]] = []
    for part in (p.strip().lower() for p in text.split(",")):
        if not part:
            continue
        size = parse_resolution(part, "--resolutions")
        if size not in found:
            found.append(size)
    if not found:
        raise UserError("--resolutions: expected at least one WIDTHxHEIGHT")
    return found


def resolution_label(size: tuple[int, int]) -> str:
    """(640, 480) -> '640x480', the contract's form."""
    return f"{size[0]}x{size[1]}"


def robot_policy(option: Option) -> str:
    """The robot's `--policy` for an option measured on the daemons (`elastic`: the bench's
    variant without segments; `elastic-segments`: the runtime's `elastic`)."""
    if option == OFF:
        raise ValueError("the assistant off is not run on the daemons")
    if option == ELASTIC:
        return ELASTIC_SUFFIXES_POLICY
    return ELASTIC if option == ELASTIC_SEGMENTS else f"option:{option}"


@dataclass(frozen=True)
class Timing:
    """Table III and IV figures of one option at one resolution, from its measured frames."""

    update_hz: float | None
    t_o_s: float | None
    t_p_s: float | None
    t_c_s: float | None
    t_f_s: float | None
    frame_latencies_s: tuple[float, ...]
    """Each measured frame's t_f: the closed loop draws its latencies from these."""


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def update_hz(window: Sequence[Record]) -> float | None:
    """Frames completed per second over the window (completion times `at`); None below two."""
    times = sorted(float(r["at"]) for r in window if r.get("at") is not None)
    if len(times) < 2 or times[-1] <= times[0]:
        return None
    return (len(times) - 1) / (times[-1] - times[0])


def timing(window: Sequence[Record]) -> Timing:
    """The figures of a window of telemetry records (one per frame, warm-up left out)."""
    latencies = tuple(float(r["latency_s"]) for r in window)
    return Timing(
        update_hz=update_hz(window),
        t_o_s=_mean([float(r["transfer_s"]) for r in window]),
        t_p_s=_mean([float(r["cloud_s"]) for r in window]),
        t_c_s=_mean([float(r["prefix_s"]) + float(r["suffix_local_s"]) for r in window]),
        t_f_s=_mean(latencies),
        frame_latencies_s=latencies,
    )


NO_TIMING = Timing(None, None, None, None, None, ())


@dataclass(frozen=True)
class LoopFigures:
    """Table V of one option at one resolution: collisions over the maneuvers driven."""

    collisions: int
    maneuvers: int
    distance_m: float = 0.0
    """Mean distance driven per maneuver: an assistant that stops the robot far from every
    obstacle (or never lets it start) has no collisions either."""
    min_clearance_m: float | None = None
    """The smallest clearance (robot's edge to a face) of the maneuvers without a collision;
    None when every one collided."""


def contract_row(
    option: Option,
    size: tuple[int, int],
    figures: Timing,
    loop: LoopFigures | None,
    lost: int,
) -> dict[str, Any]:
    """One result row with exactly the contract's keys (None where a figure was not measured:
    no timing for the assistant off, no collisions for an option not driven in the loop)."""
    row = {
        "option": option,
        "resolution": resolution_label(size),
        "update_hz": figures.update_hz,
        "t_o_s": figures.t_o_s,
        "t_p_s": figures.t_p_s,
        "t_c_s": figures.t_c_s,
        "t_f_s": figures.t_f_s,
        "collisions": loop.collisions if loop is not None else None,
        "maneuvers": loop.maneuvers if loop is not None else 0,
        "lost": lost,
    }
    assert tuple(row) == ROW_KEYS
    return row
