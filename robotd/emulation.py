"""Run-time emulation of a slower robot and a changing uplink, for one host without root.

On one host the robot daemon computes as fast as the cloud daemons beside it and talks to them
over loopback, so offloading never pays and a link never degrades. Two knobs make the robot
behave like a real one, and both are *emulation*, printed as such:

- `--robot-slowdown F`: after each robot-side model run (a prefix, a local suffix, the whole
  model) the robot waits (F−1)× the time that run took, so each run takes F× its time on this
  host (`Slowdown`). The wait costs no CPU, so the cloud daemons sharing the host's cores are not
  slowed by it; a real CPU quota (cgroup, root) is what `elasticfog testbed` does instead.
  `robot_class(F)` names, roughly, what kind of robot computer F stands for. The robot's
  startup profile is scaled the same way (`scaled_profile`), as if it had been timed on the
  emulated robot: the policies start from the emulated speed and follow it online.
- the uplink: the application token bucket of `robotd.frame_path.pacing`, its rate set per phase.
Phase
  links serialise every request (`EMULATED_LINK_BURST_BYTES`, one Ethernet frame, passes at
  once), like a real link of that rate; a bigger burst would let a small JPEG through for free.

`--phases FILE.yaml` changes both while the robot runs, at phase boundaries counted in frames
(the frame loop calls `Emulation.enter(n)` before frame n; the robot's telemetry records the
phase). The file (`load_phases`), every key but `name` and `frames` optional:

    phases:
      - {name: good link, frames: 120, uplink_mbit: 8, slowdown: 4}
      - {name: bad link, frames: 120, uplink_mbit: 0.2}   # slowdown 4 still
      - {name: no pacing, frames: 60, uplink_mbit: null}  # loopback as it is

A phase that leaves out `uplink_mbit` or `slowdown` keeps the previous phase's (the first phase
starts from `--uplink-mbit` and `--robot-slowdown`); `uplink_mbit: null` turns pacing off. After
the last phase its settings hold. Unknown keys are errors; each problem is one line naming it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from common.errors import UserError
from common.yaml_files import format_validation_error, read_yaml
from robotd.frame_path.pacing import BITS_PER_BYTE, BITS_PER_MBIT, TokenBucket

if TYPE_CHECKING:
    import onnxruntime as ort

log = logging.getLogger("robotd")

MAX_SLOWDOWN = 1000.0
"""A robot a thousand times slower than this host is no longer a robot worth emulating."""
EMULATED_LINK_BURST_BYTES = 1500
"""Bytes a phase link lets through at once: one Ethernet frame, the rest waits for the rate."""
CANCEL_POLL_S = 0.005
"""How often a slowdown wait looks at its run's cancel flag (a hedged run the cloud beat)."""
MAX_PHASE_NAME = 40

# What F stands for, roughly: F× slower than a desktop or server x86 core, for CNN inference
# on the CPU. Upper bounds of F, and the class below each.
ROBOT_CLASSES: tuple[tuple[float, str], ...] = (
    (1.5, "as fast as this host"),
    (2.5, "a laptop-class CPU"),
    (10.0, "a Raspberry Pi 4 / Jetson Nano class CPU"),
    (math.inf, "a microcontroller-class robot computer"),
)

Outputs = Mapping[str, Any]
R = TypeVar("R")


def robot_class(factor: float) -> str:
    """The kind of robot computer a slowdown of `factor` stands for (roughly)."""
    for upper, name in ROBOT_CLASSES:
        if factor <= upper:
            return name
    return ROBOT_CLASSES[-1][1]


def emulation_note(uplink_mbit: float | None, slowdown: float) -> str:
    """What the robot's startup line says of a fixed emulation ("" without one)."""
    uplink = f", uplink paced to {uplink_mbit:g} Mbit/s (emulation)" if uplink_mbit else ""
    if slowdown == 1.0:
        return uplink
    robot = f"robot {slowdown:g}× slower than this host (emulation: {robot_class(slowdown)})"
    return f"{uplink}, {robot}"


def check_slowdown(factor: float, what: str = "--robot-slowdown") -> float:
    """`factor` if it is a slowdown the robot can emulate, else UserError naming `what`."""
    if not (math.isfinite(factor) and 1.0 <= factor <= MAX_SLOWDOWN):
        raise UserError(f"{what} {factor:g}: expected a factor from 1 to {MAX_SLOWDOWN:g}")
    return float(factor)


class Slowdown:
    """Stretches robot-side model runs to `factor` × their time here, by waiting afterwards.

    Thread-safe: the frame loop and the low-priority local-run thread both run through it, and
    a phase change sets `factor` from the frame loop. `stop` (the daemon's stop flag) cuts a
    wait short; so does the run's own cancel flag (`RunOptions.terminate`, set when the cloud
    beat a hedged local run)."""

    def __init__(
        self,
        factor: float = 1.0,
        *,
        stop: threading.Event | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self._factor = check_slowdown(factor)
        self._stop = stop or threading.Event()
        self._clock = clock

    @property
    def factor(self) -> float:
        return self._factor

    @factor.setter
    def factor(self, value: float) -> None:
        self._factor = check_slowdown(value)  # a float assignment is atomic

    def run(self, fn: Callable[[ort.RunOptions | None], R], options: ort.RunOptions | None) -> R:
        """`fn(options)`, then a wait of (factor−1)× the time it took."""
        started = self._clock()
        result = fn(options)
        extra_s = (self._factor - 1.0) * (self._clock() - started)
        if extra_s > 0:
            self._wait(extra_s, options)
        return result

    def stretched(
        self, fn: Callable[[ort.RunOptions | None], R]
    ) -> Callable[[ort.RunOptions | None], R]:
        """`fn` running through `run` (for a job handed to another thread)."""
        return lambda options: self.run(fn, options)

    def _wait(self, seconds: float, options: ort.RunOptions | None) -> None:
        until = self._clock() + seconds
        while True:  # bounded by `until`
            left = until - self._clock()
            if left <= 0 or (options is not None and options.terminate):
                return
            if self._stop.wait(min(left, CANCEL_POLL_S) if options is not None else left):
                return


# -- phases ----------------------------------------------------------------------------------------
class PhaseSpec(BaseModel):
    """One phase as written in a file: how long it lasts and what it changes."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(
        min_length=1,
        max_length=MAX_PHASE_NAME,
        description="Label of the phase (telemetry, tables, plots).",
    )
    frames: int = Field(ge=1, description="Frames the phase lasts.")
    uplink_mbit: float | None = Field(
        default=None,
        gt=0,
        allow_inf_nan=False,
        description="Emulated uplink in Mbit/s (null: not paced); left out: the previous phase's.",
    )
    slowdown: float | None = Field(
        default=None,
        ge=1,
        le=MAX_SLOWDOWN,
        allow_inf_nan=False,
        description="Robot slowdown factor; left out: the previous phase's.",
    )

    @property
    def sets_uplink(self) -> bool:
        return "uplink_mbit" in self.model_fields_set


class PhasesFile(BaseModel):
    """The robot's `--phases` file."""

    model_config = ConfigDict(extra="forbid")

    phases: list[PhaseSpec] = Field(min_length=1, description="Phases, in order.")

    @model_validator(mode="after")
    def _unique_names(self) -> PhasesFile:
        check_unique_names(self.phases)
        return self


def check_unique_names(phases: Sequence[PhaseSpec]) -> None:
    """ValueError naming a phase name used twice (tables and plots tell phases by name)."""
    seen: set[str] = set()
    for i, phase in enumerate(phases):
        if phase.name in seen:
            raise ValueError(f"phases[{i}].name {phase.name!r} is used by an earlier phase")
        seen.add(phase.name)


@dataclass(frozen=True)
class Phase:
    """A phase with every setting resolved: frames `first` .. `first + frames - 1`."""

    name: str
    first: int
    frames: int
    uplink_mbit: float | None
    slowdown: float

    @property
    def end(self) -> int:
        """The first frame after this phase."""
        return self.first + self.frames

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "frames": self.frames,
            "uplink_mbit": self.uplink_mbit,
            "slowdown": self.slowdown,
        }


def resolve_phases(
    specs: Sequence[PhaseSpec], *, uplink_mbit: float | None = None, slowdown: float = 1.0
) -> list[Phase]:
    """Phases with their first frame and every setting filled in (a setting left out keeps the
    previous phase's; the first phase starts from `uplink_mbit` and `slowdown`)."""
    phases: list[Phase] = []
    first = 0
    for spec in specs:
        if spec.sets_uplink:
            uplink_mbit = spec.uplink_mbit
        if spec.slowdown is not None:
            slowdown = spec.slowdown
        phases.append(Phase(spec.name, first, spec.frames, uplink_mbit, slowdown))
        first += spec.frames
    return phases


def load_phases(
    path: str | Path, *, uplink_mbit: float | None = None, slowdown: float = 1.0
) -> list[Phase]:
    """The robot's `--phases` file, resolved (`resolve_phases`); UserError naming the problem."""
    file = Path(path)
    source = f"--phases {file}"
    data = read_yaml(file, "--phases")  # strict: a key given twice is refused, naming both lines
    if not isinstance(data, dict):
        raise UserError(f"{source}: expected a mapping with a list of phases")
    try:
        parsed = PhasesFile.model_validate(data)
    except ValidationError as exc:
        raise UserError(f"{source}: {format_validation_error(exc, PhasesFile)}") from None
    return resolve_phases(parsed.phases, uplink_mbit=uplink_mbit, slowdown=slowdown)


def scaled_profile(profile: dict[str, Any], factor: float) -> dict[str, Any]:
    """`robotd.robot_profile.robot_profile`'s profile as if timed on a robot `factor`× slower
    (the robot's times only; bytes and codecs do not depend on its speed)."""
    if factor == 1.0:
        return profile
    out = dict(profile, full_ms=profile["full_ms"] * factor)
    out["cuts"] = [
        dict(row, prefix_ms=row["prefix_ms"] * factor, suffix_ms=row["suffix_ms"] * factor)
        for row in profile["cuts"]
    ]
    return out


class Emulation:
    """The robot's emulated speed and uplink over its run: `enter(n)` before frame n applies the
    phase n is in (once per phase) and returns its name (None without phases).

    `set_uplink(mbit)` replaces the request sender's bucket (None: not paced); a phase link
    keeps its bucket across phases, so requests still queued on it keep their place."""

    def __init__(
        self,
        phases: Sequence[Phase],
        slowdown: Slowdown,
        set_uplink: Callable[[TokenBucket | None], None],
        *,
        robot: str = "robot",
    ) -> None:
        self.phases = list(phases)
        self.slowdown = slowdown
        self._set_uplink = set_uplink
        self._robot = robot
        self._bucket: TokenBucket | None = None
        self._current: Phase | None = None

    def phase_at(self, frame: int) -> Phase | None:
        """The phase frame `frame` is in (the last one past the end; None without phases)."""
        for phase in self.phases:
            if frame < phase.end:
                return phase
        return self.phases[-1] if self.phases else None

    def phase_name(self, frame: int) -> str | None:
        """The name of the phase frame `frame` is in (None without phases)."""
        phase = self.phase_at(frame)
        return None if phase is None else phase.name

    def enter(self, frame: int) -> str | None:
        phase = self.phase_at(frame)
        if phase is None:
            return None
        if phase is not self._current:
            self._current = phase
            self._apply(phase)
        return phase.name

    def _apply(self, phase: Phase) -> None:
        self.slowdown.factor = phase.slowdown
        if phase.uplink_mbit is None:
            self._set_uplink(None)
        else:
            rate = phase.uplink_mbit * BITS_PER_MBIT / BITS_PER_BYTE
            if self._bucket is None:
                self._bucket = TokenBucket(rate, EMULATED_LINK_BURST_BYTES)
            else:
                self._bucket.set_rate(rate)
            self._set_uplink(self._bucket)
        link = "not paced" if phase.uplink_mbit is None else f"{phase.uplink_mbit:g} Mbit/s"
        log.info(
            "%s: phase %r from frame %d: uplink %s, robot %g× slower than this host "
            "(emulation: %s)",
            self._robot,
            phase.name,
            phase.first,
            link,
            phase.slowdown,
            robot_class(phase.slowdown),
        )
