"""What ElasticROS's Tables I-III share on the testbed: one robot against one cloud daemon.

The three experiments (`table1`, `glitch` for Table II, `table3`) run one robot after another,
one run per policy, against `edge-1` on the same four hosts, with a deadline far above a full
offload at the slowest cap (so "cloud" is measured, not cut off), and bound each run by its
frames. Their frames are split into a warm-up left out and the phases the experiment measures
(`preset_split`), and their JSON leaves the per-frame traces out (`public`).
"""

from __future__ import annotations

from typing import Any, TypeVar

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


def fleet_spec(tf: TestbedFleet, options: BenchOptions, tag: str) -> FleetSpec:
    """The single-edge fleet of a run: `edge-1` serving, the bench's model and shape."""
    return FleetSpec(
        fleet=tf.next_fleet_name(tag),
        clouds=(CLOUD,),
        model=options.model,
        input_shape=options.input_shape,
        deadline_s=DEADLINE_S,
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


def public(result: dict[str, Any]) -> dict[str, Any]:
    """The `--json` of an experiment: its settings and rows, the per-frame traces left out."""
    rows = [{k: v for k, v in r.items() if k != "trace"} for r in result["results"]]
    return {"settings": result["settings"], "results": rows}
