"""ElasticROS Table III on the testbed: the robot's CPU availability drops, then recovers.

One robot run per policy against one cloud daemon (`edge-1`), uplink capped at 10 Mbit/s. The
robot's host starts with a whole core (`HIGH_CPU`), drops to `robot_cpu` of a core (the cgroup
quota changes while the robot computes), then gets the whole core back. Each change splits the
frames into before / on / after as in Table II (`stats.phases`): "on" lasts until the policy
settles. A policy that keeps computing on the robot pays the lower quota in full; one that moves
work to the cloud pays the uplink instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from common.defaults import DEFAULT_CAMERA_SOURCE

from .options import BenchOptions, open_fleet
from .report import fmt, md_table, save_plot, use_agg
from .runner import TestbedFleet
from .single_edge import (
    CHANGE_WAIT_S,
    DEADLINE_S,
    HOSTS,
    SingleEdgeResult,
    fleet_spec,
    preset_split,
    run_timeout_s,
)
from .stats import Phases, Record, WindowSummary, by_frame, lost_frames, phases

POLICIES = ("elastic", "elastic-nohedge", "robot", "cloud:jpeg80", "cloud")
UPLINK_MBIT = 10.0
HIGH_CPU = 1.0
# Frames of one run: warm-up (left out), whole core, low quota, whole core again.
FULL_SPLIT = (10, 25, 40, 40)
QUICK_SPLIT = (4, 12, 20, 20)
# What a row's trace keeps of each telemetry record (the plot's).
TRACE_KEYS = ("frame", "action", "latency_s", "robot_cpu_s", "fallback")


@dataclass(frozen=True)
class Table3Frames:
    """Frames of one run: warm-up (left out), whole core, low quota, whole core again."""

    warmup: int
    high: int
    low: int
    high_again: int


@dataclass(frozen=True)
class Table3Settings:
    """The runs' settings; the fields, in order, are the keys of its JSON object."""

    model: str
    input_shape: list[int]
    uplink_mbit: float
    high_cpu: float
    low_cpu: float
    frames: Table3Frames
    deadline_s: float = DEADLINE_S
    source: str = DEFAULT_CAMERA_SOURCE
    """The robot's camera (`--source`)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Table3Row:
    """One policy through the drop and the recovery: the phases around each change, frames
    lost, where the changes and the measurement began, and the per-frame trace (for the plot,
    not the JSON)."""

    policy: str
    drop: Phases
    recover: Phases
    lost: int
    drop_frame: int
    recover_frame: int
    measured_from_frame: int
    trace: list[Record]

    def windows(self) -> tuple[WindowSummary, ...]:
        """The five phases in order: before, on and after the drop, on and after
        the recovery (the recovery's "before" is the drop's "after")."""
        d, r = self.drop, self.recover
        return d.before, d.on, d.after, r.on, r.after

    def to_json(self) -> dict[str, Any]:
        """{"policy", the five phases by name, the settle frames of each change, "lost", the
        frames of the changes and of the measurement's start}; the trace left out."""
        before, drop_on, drop_after, recover_on, recover_after = self.windows()
        return {
            "policy": self.policy,
            "before": before.to_json(),
            "drop_on": drop_on.to_json(),
            "drop_after": drop_after.to_json(),
            "drop_settle_frames": self.drop.settle_frames,
            "recover_on": recover_on.to_json(),
            "recover_after": recover_after.to_json(),
            "recover_settle_frames": self.recover.settle_frames,
            "lost": self.lost,
            "drop_frame": self.drop_frame,
            "recover_frame": self.recover_frame,
            "measured_from_frame": self.measured_from_frame,
        }


Table3Result = SingleEdgeResult[Table3Settings, Table3Row]


def frame_split(options: BenchOptions) -> tuple[int, int, int, int]:
    preset = preset_split(options, FULL_SPLIT, QUICK_SPLIT)
    if preset is not None:
        return preset
    n = int(options.frames or 0)
    warmup, high = max(1, n // 12), max(3, n // 5)
    low = max(3, (n - warmup - high) // 2)
    return warmup, high, low, max(3, n - warmup - high - low)


def run_one(tf: TestbedFleet, options: BenchOptions, policy: str) -> Table3Row:
    warmup, high, low, again = frame_split(options)
    frames = warmup + high + low + again
    tf.shape_robot(UPLINK_MBIT)
    robot = tf.start_robot(policy, frames=frames, cpu_fraction=HIGH_CPU)
    start = tf.measure_from + warmup
    tf.follower.wait_frame(start + high - 1, timeout_s=CHANGE_WAIT_S, procs=[robot])
    tf.cpu_robot(options.robot_cpu)
    drop_frame = tf.follower.last_frame() + 1
    tf.follower.wait_frame(drop_frame + low - 1, timeout_s=CHANGE_WAIT_S, procs=[robot])
    tf.cpu_robot(HIGH_CPU)
    recover_frame = tf.follower.last_frame() + 1
    options.log(f"{policy}: CPU dropped at frame {drop_frame}, back at {recover_frame}")
    records = by_frame(tf.finish_robot(run_timeout_s(frames)))
    return Table3Row(
        policy=policy,
        drop=phases(records, start, drop_frame, stop=recover_frame),
        recover=phases(records, drop_frame, recover_frame),
        lost=len(lost_frames(records, frames)),
        drop_frame=drop_frame,
        recover_frame=recover_frame,
        measured_from_frame=start,
        trace=[{k: r.get(k) for k in TRACE_KEYS} for r in records],
    )


def run(options: BenchOptions, policies: Sequence[str] = POLICIES) -> Table3Result:
    options.check()
    warmup, high, low, again = frame_split(options)
    results = []
    with open_fleet(options, hosts=HOSTS) as tf:
        tf.launch(fleet_spec(tf, options, "t3-"))
        for policy in policies:
            results.append(run_one(tf, options, policy))
    settings = Table3Settings(
        model=options.model,
        input_shape=list(options.input_shape),
        uplink_mbit=UPLINK_MBIT,
        high_cpu=HIGH_CPU,
        low_cpu=options.robot_cpu,
        frames=Table3Frames(warmup=warmup, high=high, low=low, high_again=again),
        source=options.source,
    )
    return SingleEdgeResult(settings, results)


def markdown(result: Table3Result) -> str:
    """One row per policy; each cell lists the five phases: before, on and after the drop, on
    and after the recovery."""
    s = result.settings
    phases = (
        f"before ({s.high_cpu:g} core) / on / after (at {s.low_cpu:g}) / on / "
        f"after (at {s.high_cpu:g} again)"
    )
    header = [
        "policy",
        f"latency (s): {phases}",
        "robot CPU (s)",
        "energy (J)",
        "main action",
        "settle (drop / recovery)",
        "lost",
    ]
    rows: list[list[str]] = []
    for r in result.results:
        windows = r.windows()
        rows.append(
            [
                r.policy,
                " / ".join(fmt(w.mean_latency_s, 3) for w in windows),
                " / ".join(fmt(w.robot_cpu_s, 4) for w in windows),
                " / ".join(fmt(w.energy_j, 2) for w in windows),
                " / ".join(str(w.main_action) for w in windows),
                f"{fmt(r.drop.settle_frames)} / {fmt(r.recover.settle_frames)}",
                str(r.lost),
            ]
        )
    return md_table(header, rows) + "\n"


def plot(result: Table3Result, out_dir: Path) -> list[Path]:
    use_agg()
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    spans = []
    for r in result.results:
        trace = [t for t in r.trace if t["frame"] >= r.measured_from_frame]
        ax.plot(
            [t["frame"] - r.drop_frame for t in trace],
            [t["latency_s"] for t in trace],
            marker=".",
            label=r.policy,
        )
        spans.append(r.recover_frame - r.drop_frame)
    if spans:
        ax.axvspan(0, min(spans), color="orange", alpha=0.15)
    s = result.settings
    ax.set_title(
        f"robot CPU {s.high_cpu:g} → {s.low_cpu:g} → {s.high_cpu:g} core "
        f"(shaded: low quota), uplink {s.uplink_mbit:g} Mbit/s"
    )
    ax.set_yscale("log")
    ax.set_xlabel("frames since the quota dropped")
    ax.set_ylabel("latency (s)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    return [save_plot(fig, out_dir / "table3.png")]
