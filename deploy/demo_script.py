"""The demo's script: phases of an emulated robot and link, and when the serving deployment dies.

`elasticfog demo` runs a script of phases, each a number of frames with an emulated uplink and
robot slowdown (`robotd.emulation`: the robot itself switches at the phase boundaries, counted in
frames); one phase may SIGKILL the deployment serving the robot at its first frame, to show a
failover. The default script ships with the package (`demo_scripts/default.yaml`);
`--script FILE.yaml` runs one's own:

    description: my robot on a flaky Wi-Fi
    slowdown: 4            # robot slowdown of phases that set none (default 1: this host's speed)
    uplink_mbit: 8         # uplink of phases that set none (default: not paced)
    fps: 15                # robot frame rate (default: the demo's --fps)
    phases:
      - {name: good link, frames: 100}
      - {name: bad link, frames: 100, uplink_mbit: 0.2}
      - {name: failover, frames: 80, uplink_mbit: 8, kill_service: true}

A phase that leaves out `uplink_mbit` or `slowdown` keeps the previous phase's; `uplink_mbit:
null` turns pacing off (loopback as it is). Unknown keys, a name used twice, a second
`kill_service` phase or a bad value are one-line errors naming the file and the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from common.errors import UserError
from common.yaml_files import format_validation_error, read_yaml
from robotd.emulation import (
    MAX_SLOWDOWN,
    Phase,
    PhaseSpec,
    check_unique_names,
    resolve_phases,
)

DEFAULT_SCRIPT = Path(__file__).resolve().parent / "demo_scripts" / "default.yaml"
SINGLE_PHASE_NAME = "run"
"""The one phase of `elasticfog demo --frames N` (no script)."""


class DemoPhase(PhaseSpec):
    """A phase of the demo: the robot's emulation, and optionally a failover."""

    kill_service: bool = Field(
        default=False,
        description="SIGKILL the deployment serving the robot at this phase's first frame.",
    )


class DemoScriptFile(BaseModel):
    """A `--script` file."""

    model_config = ConfigDict(extra="forbid")

    description: str = Field(default="", description="What the script shows, one line.")
    slowdown: float = Field(
        default=1.0,
        ge=1,
        le=MAX_SLOWDOWN,
        allow_inf_nan=False,
        description="Robot slowdown of the phases that set none before them.",
    )
    uplink_mbit: float | None = Field(
        default=None,
        gt=0,
        allow_inf_nan=False,
        description="Uplink (Mbit/s) of the phases that set none before them (null: not paced).",
    )
    fps: float | None = Field(
        default=None, gt=0, allow_inf_nan=False, description="Robot frame rate."
    )
    phases: list[DemoPhase] = Field(min_length=1, description="Phases, in order.")

    @model_validator(mode="after")
    def _checks(self) -> DemoScriptFile:
        check_unique_names(self.phases)
        kills = [i for i, p in enumerate(self.phases) if p.kill_service]
        if len(kills) > 1:
            raise ValueError(
                f"phases[{kills[1]}].kill_service: only one phase may kill the serving "
                f"deployment (phases[{kills[0]}] already does; the demo has two deployments)"
            )
        return self


@dataclass(frozen=True)
class DemoScript:
    """A script resolved: every phase's settings filled in, and the kill frame."""

    phases: tuple[Phase, ...]
    kill_at: int | None = None
    fps: float | None = None
    description: str = ""
    source: str = "default"

    @property
    def frames(self) -> int:
        return sum(p.frames for p in self.phases)

    def with_overrides(
        self,
        *,
        uplink_mbit: float | None = None,
        slowdown: float | None = None,
        kill_at: int | None = None,
    ) -> DemoScript:
        """The same script with every phase's uplink and/or slowdown set (the demo's
        `--uplink-mbit`, `--robot-slowdown`) and/or the kill moved (`--kill-service-at`)."""
        phases = tuple(
            replace(
                p,
                uplink_mbit=p.uplink_mbit if uplink_mbit is None else uplink_mbit,
                slowdown=p.slowdown if slowdown is None else slowdown,
            )
            for p in self.phases
        )
        return replace(self, phases=phases, kill_at=self.kill_at if kill_at is None else kill_at)

    def robot_phases_yaml(self) -> str:
        """The robot's `--phases` file for this script (`robotd.emulation.load_phases`)."""
        return yaml.safe_dump({"phases": [p.to_json() for p in self.phases]}, sort_keys=False)


def script_from_dict(data: Any, source: str) -> DemoScript:
    """Validate and resolve a script mapping; UserError naming `source` and the field."""
    if not isinstance(data, dict):
        raise UserError(f"{source}: expected a mapping with a list of phases")
    try:
        parsed = DemoScriptFile.model_validate(data)
    except ValidationError as exc:
        raise UserError(f"{source}: {format_validation_error(exc, DemoScriptFile)}") from None
    phases = resolve_phases(parsed.phases, uplink_mbit=parsed.uplink_mbit, slowdown=parsed.slowdown)
    kill_at = next(
        (p.first for p, s in zip(phases, parsed.phases, strict=True) if s.kill_service), None
    )
    return DemoScript(
        phases=tuple(phases),
        kill_at=kill_at,
        fps=parsed.fps,
        description=parsed.description,
        source=source,
    )


def load_script(path: str | Path) -> DemoScript:
    """A `--script` file; UserError naming the file and the problem."""
    file = Path(path)
    return script_from_dict(read_yaml(file, "--script"), f"--script {file}")


def default_script() -> DemoScript:
    """The script `elasticfog demo` runs when given none."""
    script = load_script(DEFAULT_SCRIPT)
    return replace(script, source="default")


def single_phase(
    frames: int, *, uplink_mbit: float | None, slowdown: float, kill_at: int | None
) -> DemoScript:
    """`elasticfog demo --frames N`: one phase of N frames."""
    if frames < 1:
        raise UserError(f"--frames {frames}: expected at least 1 frame")
    phase = Phase(SINGLE_PHASE_NAME, 0, frames, uplink_mbit, slowdown)
    return DemoScript(phases=(phase,), kill_at=kill_at, source=f"--frames {frames}")


def check_positive(value: float | None, option: str) -> None:
    """UserError unless `value` is None or a positive finite number."""
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise UserError(f"{option} {value}: expected a positive number")
