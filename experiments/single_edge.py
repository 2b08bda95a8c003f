"""What ElasticROS's Tables I-III share on the testbed: one robot against one cloud daemon.

The three experiments (`table1`, `glitch` for Table II, `table3`) run one robot after another,
one run per policy, against `edge-1` on the same four hosts, with a deadline far above a full
offload at the slowest cap (so "cloud" is measured, not cut off), and bound each run by its
frames. Their frames are split into a warm-up left out and the phases the experiment measures
(`preset_split`). Each gives a `SingleEdgeResult`: its settings and one row per run, typed; its
`--json` (`SingleEdgeResult.public`) is written from them, the per-frame traces the plots use
left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from .fleet import FleetSpec
from .options import BenchOptions
from .runner import TestbedFleet

HOSTS = ("registry", "robot", "edge-1", "bench")
CLOUD = "edge-1"
DEADLINE_S = 15.0
"""Far above a full offload at 0.5 Mbit/s (3.9 s for 230 KB): "cloud" is measured, not cut off."""
RUN_SLACK_S = 120.0
"""A run's bound besides its frames' deadlines (the robot's start-up and profile)."""
CHANGE_WAIT_S = 300.0
"""Bound of the wait for the frame at which a condition changes (uplink cap, CPU quota)."""

Split = TypeVar("Split", bound=tuple[int, ...])


class JsonObject(Protocol):
    """A typed part of a result that writes its own JSON object (keys are the contract)."""

    def to_json(self) -> dict[str, Any]: ...


Settings = TypeVar("Settings", bound=JsonObject)
Row = TypeVar("Row", bound=JsonObject)


@dataclass(frozen=True)
class SingleEdgeResult(Generic[Settings, Row]):
    """What one of the experiments gives: its settings and one row per run."""

    settings: Settings
    results: list[Row]

    def public(self) -> dict[str, Any]:
        """The `--json` of the experiment: {"settings": ..., "results": [rows]}."""
        return {
            "settings": self.settings.to_json(),
            "results": [row.to_json() for row in self.results],
        }


def fleet_spec(tf: TestbedFleet, options: BenchOptions, tag: str) -> FleetSpec:
    """The single-edge fleet of a run: `edge-1` serving, the bench's model, shape and source."""
    return FleetSpec(
        fleet=tf.next_fleet_name(tag),
        clouds=(CLOUD,),
        model=options.model,
        input_shape=options.input_shape,
        deadline_s=DEADLINE_S,
        source=options.source,
    )


def run_timeout_s(frames: int) -> float:
    """How long a robot run of `frames` frames may take: every frame at its deadline, and slack."""
    return RUN_SLACK_S + frames * (DEADLINE_S + 1)


def preset_split(options: BenchOptions, full: Split, quick: Split) -> Split | None:
    """The experiment's own frame split when --frames is not given (`quick` with --quick);
    None: split --frames N the experiment's way."""
    if options.frames is not None:
        return None
    return quick if options.quick else full
