"""ElasticROS Table II on the testbed: the robot's uplink cap drops while it streams.

One robot run per policy against one cloud daemon (`edge-1`): the uplink is capped at A Mbit/s,
and once the robot has reported `before` measured frames the cap is changed to B Mbit/s with
`tc class change` while its frames are in flight. The frames are split into before / on / after
the change ("on" lasts until the policy settles on its final action, see `stats.phases`), each
with its mean latency, robot CPU and energy per frame; `settle_frames` counts frames from the
change until the policy settled, `lost` the frames asked for and never reported.

`--json` prints `{"results": [{"policy", "before_mean_latency_s", "on_mean_latency_s",
"after_mean_latency_s", "settle_frames", "lost", ...}]}`. Table II runs 10→3, 5→1 and 10→1.
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
from .stats import Phases, Record, by_frame, lost_frames, phases

POLICIES = ("elastic", "elastic-nohedge", "cloud:jpeg80", "cloud", "robot")
TABLE2_GLITCHES = ((10.0, 3.0), (5.0, 1.0), (10.0, 1.0))
# Frames of one run: warm-up (left out), before the change, after it.
FULL_SPLIT = (10, 20, 50)
QUICK_SPLIT = (4, 10, 24)
# What a row's trace keeps of each telemetry record (the plot's).
TRACE_KEYS = ("frame", "action", "latency_s", "bytes_up", "fallback")


@dataclass(frozen=True)
class GlitchSettings:
    """The runs' settings; the fields, in order, are the keys of its JSON object."""

    model: str
    input_shape: list[int]
    robot_cpu: float
    warmup_frames: int
    before_frames: int
    after_frames: int
    deadline_s: float = DEADLINE_S
    source: str = DEFAULT_CAMERA_SOURCE
    """The robot's camera (`--source`)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class GlitchRow:
    """One policy through one glitch: the phases around the change, frames lost, where the
    change and the measurement began, and the per-frame trace (for the plot, not the JSON)."""

    policy: str
    from_mbit: float
    to_mbit: float
    phases: Phases
    lost: int
    change_frame: int
    measured_from_frame: int
    trace: list[Record]

    def to_json(self) -> dict[str, Any]:
        """The row of the `--json` contract (the module docstring), the trace left out."""
        ph = self.phases
        return {
            "policy": self.policy,
            "from_mbit": self.from_mbit,
            "to_mbit": self.to_mbit,
            "before_mean_latency_s": ph.before.mean_latency_s,
            "on_mean_latency_s": ph.on.mean_latency_s,
            "after_mean_latency_s": ph.after.mean_latency_s,
            "settle_frames": ph.settle_frames,
            "lost": self.lost,
            "change_frame": self.change_frame,
            "measured_from_frame": self.measured_from_frame,
            "before": ph.before.to_json(),
            "on": ph.on.to_json(),
            "after": ph.after.to_json(),
        }


GlitchResult = SingleEdgeResult[GlitchSettings, GlitchRow]


def frame_split(options: BenchOptions) -> tuple[int, int, int]:
    """(warm-up, before, after) frames; --frames N splits N as 1/8, 1/4, 5/8."""
    preset = preset_split(options, FULL_SPLIT, QUICK_SPLIT)
    if preset is not None:
        return preset
    n = int(options.frames or 0)
    warmup, before = max(1, n // 8), max(3, n // 4)
    return warmup, before, max(3, n - warmup - before)


def run_one(
    tf: TestbedFleet,
    options: BenchOptions,
    policy: str,
    from_mbit: float,
    to_mbit: float,
) -> GlitchRow:
    """One policy through one glitch on a launched fleet; its result row."""
    warmup, before, after = frame_split(options)
    frames = warmup + before + after
    tf.shape_robot(from_mbit)
    robot = tf.start_robot(policy, frames=frames, cpu_fraction=options.robot_cpu)
    start = tf.measure_from + warmup
    # Change the cap as soon as the last "before" frame is reported: the next one is in flight.
    tf.follower.wait_frame(start + before - 1, timeout_s=CHANGE_WAIT_S, procs=[robot])
    tf.shape_robot(to_mbit)
    change_frame = tf.follower.last_frame() + 1
    options.log(f"{policy}: uplink {from_mbit:g} -> {to_mbit:g} Mbit/s at frame {change_frame}")
    records = by_frame(tf.finish_robot(run_timeout_s(frames)))
    return GlitchRow(
        policy=policy,
        from_mbit=from_mbit,
        to_mbit=to_mbit,
        phases=phases(records, start, change_frame),
        lost=len(lost_frames(records, frames)),
        change_frame=change_frame,
        measured_from_frame=start,
        trace=[{k: r.get(k) for k in TRACE_KEYS} for r in records],
    )


def run(
    options: BenchOptions,
    from_mbit: float,
    to_mbit: float,
    policies: Sequence[str] = POLICIES,
) -> GlitchResult:
    """`bench glitch`: every policy through one glitch."""
    return run_table2(options, [(from_mbit, to_mbit)], policies)


def run_table2(
    options: BenchOptions,
    glitches: Sequence[tuple[float, float]] = TABLE2_GLITCHES,
    policies: Sequence[str] = POLICIES,
) -> GlitchResult:
    """Every policy through every glitch, on one testbed."""
    options.check()
    warmup, before, after = frame_split(options)
    results = []
    with open_fleet(options, hosts=HOSTS) as tf:
        tf.launch(fleet_spec(tf, options, "gl-"))
        for from_mbit, to_mbit in glitches:
            for policy in policies:
                results.append(run_one(tf, options, policy, from_mbit, to_mbit))
    settings = GlitchSettings(
        model=options.model,
        input_shape=list(options.input_shape),
        robot_cpu=options.robot_cpu,
        warmup_frames=warmup,
        before_frames=before,
        after_frames=after,
        source=options.source,
    )
    return SingleEdgeResult(settings, results)


def markdown(result: GlitchResult) -> str:
    """One row per glitch and policy: latency before / on / after, robot CPU and energy per frame
    before and after, the main action before and after, frames to settle, frames lost."""
    header = [
        "glitch (Mbit/s)",
        "policy",
        "latency before / on / after (s)",
        "robot CPU before / after (s)",
        "energy before / after (J)",
        "main action",
        "settle",
        "lost",
    ]
    rows: list[list[str]] = []
    for r in result.results:
        b, o, a = r.phases.before, r.phases.on, r.phases.after
        rows.append(
            [
                f"{r.from_mbit:g}→{r.to_mbit:g}",
                r.policy,
                " / ".join(fmt(x.mean_latency_s, 3) for x in (b, o, a)),
                " / ".join(fmt(x.robot_cpu_s, 4) for x in (b, a)),
                " / ".join(fmt(x.energy_j, 2) for x in (b, a)),
                f"{b.main_action} → {a.main_action}",
                fmt(r.phases.settle_frames),
                str(r.lost),
            ]
        )
    return md_table(header, rows) + "\n"


def plot(result: GlitchResult, out_dir: Path, name: str) -> list[Path]:
    """Per glitch: latency of every frame against its index, one line per policy."""
    use_agg()
    import matplotlib.pyplot as plt

    glitches = list(dict.fromkeys((r.from_mbit, r.to_mbit) for r in result.results))
    fig, axes = plt.subplots(1, len(glitches), figsize=(5 * len(glitches), 4), squeeze=False)
    for ax, (a, b) in zip(axes[0], glitches, strict=True):
        for r in result.results:
            if (r.from_mbit, r.to_mbit) != (a, b):
                continue
            trace = [t for t in r.trace if t["frame"] >= r.measured_from_frame]
            xs = [t["frame"] - r.change_frame for t in trace]
            ax.plot(xs, [t["latency_s"] for t in trace], marker=".", label=r.policy)
        ax.axvline(0, color="grey", linestyle="--")
        ax.set_yscale("log")
        ax.set_title(f"uplink {a:g} → {b:g} Mbit/s")
        ax.set_xlabel("frames since the change")
        ax.set_ylabel("latency (s)")
        ax.grid(True, alpha=0.3)
        ax.legend()
    return [save_plot(fig, out_dir / f"{name}.png")]
