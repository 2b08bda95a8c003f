"""ElasticROS Table I on the testbed: latency, robot CPU and energy per frame vs. uplink cap.

For each uplink cap (0.5, 1, 2, 5, 20 Mbit/s by default) and each policy (robot, cloud, elastic,
neurosurgeon, ans), one robot run of N frames against one cloud daemon (`edge-1`), the robot's
host held at `robot_cpu` of a core. The first frames of each run (start-up, and the learning
policies' first explorations) are left out; the rest give the mean latency, robot CPU seconds and
energy per frame. "cloud" is node-level full offload (FogROS's way), "robot" computes everything
locally, the others choose a cut per frame.

A shared host's noise moves one run's mean by a tenth or more (the cloud's compute time, and on a
robot of a tenth of a core the phase of its quota), as much as two policies differ. `repeat` runs
each cell that many times, the policies alternated within each round, and reports the run with
the median mean latency, beside every run's mean (`runs_mean_latency_s`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from common.defaults import DEFAULT_CAMERA_SOURCE
from common.errors import UserError

from .options import BenchOptions, open_fleet
from .report import fmt, md_table, save_plot, use_agg
from .single_edge import DEADLINE_S, HOSTS, SingleEdgeResult, fleet_spec, run_timeout_s
from .stats import WindowSummary, between, by_frame, lost_frames, summary

UPLINKS_MBIT = (0.5, 1.0, 2.0, 5.0, 20.0)
POLICIES = ("robot", "cloud", "cloud:jpeg80", "elastic", "elastic-nohedge", "neurosurgeon", "ans")
FULL_FRAMES, QUICK_FRAMES = 40, 14
FULL_WARMUP, QUICK_WARMUP = 10, 4


@dataclass(frozen=True)
class Table1Settings:
    """The grid's settings; the fields, in order, are the keys of its JSON object."""

    model: str
    input_shape: list[int]
    robot_cpu: float
    frames: int
    warmup_frames: int
    deadline_s: float = DEADLINE_S
    repeat: int = 1
    source: str = DEFAULT_CAMERA_SOURCE
    """The robot's camera (`--source`)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Table1Row:
    """One cell: its uplink cap and policy, the measured window's figures, frames lost. Of
    repeated runs, the median run's window, the frames lost in all of them and each run's mean
    latency in the order they ran."""

    uplink_mbit: float
    policy: str
    window: WindowSummary
    lost: int
    runs_mean_latency_s: tuple[float | None, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """{"uplink_mbit", "policy", the window's keys, "lost"}, and "runs_mean_latency_s"
        when the cell was run more than once."""
        out = {
            "uplink_mbit": self.uplink_mbit,
            "policy": self.policy,
            **self.window.to_json(),
            "lost": self.lost,
        }
        if len(self.runs_mean_latency_s) > 1:
            out["runs_mean_latency_s"] = list(self.runs_mean_latency_s)
        return out


def median_run(runs: list[Table1Row]) -> Table1Row:
    """The run with the median mean latency (the lower one of an even count; runs without a
    measured frame count as slowest), with every run's frames lost and mean latency."""
    ranked = sorted(runs, key=lambda r: (r.window.mean_latency_s is None, r.window.mean_latency_s))
    middle = ranked[(len(ranked) - 1) // 2]
    return Table1Row(
        middle.uplink_mbit,
        middle.policy,
        middle.window,
        sum(r.lost for r in runs),
        tuple(r.window.mean_latency_s for r in runs),
    )


Table1Result = SingleEdgeResult[Table1Settings, Table1Row]


def run(
    options: BenchOptions,
    uplinks: tuple[float, ...] | list[float] = UPLINKS_MBIT,
    policies: tuple[str, ...] | list[str] = POLICIES,
    repeat: int = 1,
) -> Table1Result:
    """Run the grid: one row per (uplink, policy), the median of `repeat` alternated runs."""
    options.check()
    if repeat < 1:
        raise UserError(f"--repeat must be at least 1, got {repeat}")
    frames = options.frames_or(FULL_FRAMES, QUICK_FRAMES)
    warmup = min(FULL_WARMUP if not options.quick else QUICK_WARMUP, max(0, frames - 3))
    results: list[Table1Row] = []
    with open_fleet(options, hosts=HOSTS) as tf:
        tf.launch(fleet_spec(tf, options, "t1-"))
        for uplink in uplinks:
            tf.shape_robot(uplink)
            runs: dict[str, list[Table1Row]] = {policy: [] for policy in policies}
            for turn in range(repeat):
                for policy in runs:
                    of = f", run {turn + 1} of {repeat}" if repeat > 1 else ""
                    options.log(f"uplink {uplink:g} Mbit/s, policy {policy}{of}")
                    tf.start_robot(policy, frames=frames, cpu_fraction=options.robot_cpu)
                    records = by_frame(tf.finish_robot(run_timeout_s(frames)))
                    window = between(records, tf.measure_from + warmup)
                    lost = len(lost_frames(records, frames))
                    runs[policy].append(Table1Row(uplink, policy, summary(window), lost))
            results.extend(median_run(cell) for cell in runs.values())
    settings = Table1Settings(
        model=options.model,
        input_shape=list(options.input_shape),
        robot_cpu=options.robot_cpu,
        frames=frames,
        warmup_frames=warmup,
        repeat=repeat,
        source=options.source,
    )
    return SingleEdgeResult(settings, results)


def _row(result: Table1Result, uplink: float, policy: str) -> Table1Row | None:
    return next((r for r in result.results if r.uplink_mbit == uplink and r.policy == policy), None)


def markdown(result: Table1Result) -> str:
    """Tables (mean and median latency, robot CPU, energy per frame) with uplinks as rows."""
    rows = result.results
    uplinks = list(dict.fromkeys(r.uplink_mbit for r in rows))
    policies = list(dict.fromkeys(r.policy for r in rows))
    out = []
    figures: tuple[tuple[str, Callable[[WindowSummary], float | None], int], ...] = (
        ("mean latency per frame (s)", lambda w: w.mean_latency_s, 3),
        ("median latency per frame (s)", lambda w: w.median_latency_s, 3),
        ("robot CPU per frame (s)", lambda w: w.robot_cpu_s, 4),
        ("robot energy per frame (J)", lambda w: w.energy_j, 3),
    )
    for title, figure, digits in figures:
        table = [
            [f"{u:g}", *(fmt(_figure(_row(result, u, p), figure), digits) for p in policies)]
            for u in uplinks
        ]
        out.append(f"**{title}**\n\n" + md_table(["uplink (Mbit/s)", *policies], table))
    choices = [[f"{u:g}", *(_choice(_row(result, u, p)) for p in policies)] for u in uplinks]
    out.append(
        "**most frequent action (frames lost)**\n\n" + md_table(["uplink", *policies], choices)
    )
    if result.settings.repeat > 1:
        table = [[f"{u:g}", *(_runs(_row(result, u, p)) for p in policies)] for u in uplinks]
        out.append(
            f"**mean latency of each of the {result.settings.repeat} alternated runs (s); the "
            "tables above give the median run's figures**\n\n"
            + md_table(["uplink (Mbit/s)", *policies], table)
        )
    return "\n\n".join(out) + "\n"


def _runs(row: Table1Row | None) -> str:
    return "n/a" if row is None else " / ".join(fmt(m, 3) for m in row.runs_mean_latency_s)


def _figure(row: Table1Row | None, figure: Callable[[WindowSummary], float | None]) -> float | None:
    return None if row is None else figure(row.window)


def _choice(row: Table1Row | None) -> str:
    """The most frequent action and the frames lost, as a table cell."""
    if row is None:
        return "n/a"
    return f"{row.window.main_action} ({row.lost} lost)"


def plot(result: Table1Result, out_dir: Path) -> list[Path]:
    """Latency and energy per frame against the uplink cap, one line per policy."""
    use_agg()
    import matplotlib.pyplot as plt

    rows = result.results
    policies = list(dict.fromkeys(r.policy for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for policy in policies:
        mine = sorted((r for r in rows if r.policy == policy), key=lambda r: r.uplink_mbit)
        xs = [r.uplink_mbit for r in mine]
        axes[0].plot(xs, [r.window.mean_latency_s for r in mine], marker="o", label=policy)
        axes[1].plot(xs, [r.window.energy_j for r in mine], marker="o", label=policy)
    for ax, label in zip(axes, ("mean latency per frame (s)", "energy per frame (J)"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("robot uplink cap (Mbit/s)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    s = result.settings
    fig.suptitle(
        f"Table I on the testbed: {s.model} {'x'.join(map(str, s.input_shape))}, "
        f"robot at {s.robot_cpu:g} core"
    )
    return [save_plot(fig, out_dir / "table1.png")]
