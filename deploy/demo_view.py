"""What `elasticfog demo` shows a person: the live view while it runs, the summary tables after
it, and the `--plot` figure.

The live view (`LiveView`, rich) follows the robot's telemetry over Zenoh: the phase, its
emulated link and robot, the action of the last frame, the rolling latency and who serves the
robot; it is only a view (the numbers reported come from the telemetry file afterwards).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from deploy.demo_script import DemoScript
from deploy.demo_summary import action_order, answered_by
from robotd.emulation import Phase, robot_class

ROLLING_FRAMES = 15
"""Frames in the live view's rolling latency."""
LIVE_REFRESH_PER_S = 4
TLS_TEXT = "TLS on: mutual TLS and access control on every link (tls/ endpoints only)"


def link_text(uplink_mbit: float | None) -> str:
    return "not paced" if uplink_mbit is None else f"{uplink_mbit:g} Mbit/s"


def robot_text(slowdown: float) -> str:
    if slowdown == 1.0:
        return "this host's speed"
    return f"{slowdown:g}× slower than this host: {robot_class(slowdown)}"


def ms(seconds: float | None) -> str:
    return "n/a" if seconds is None else f"{seconds * 1000:.0f} ms"


class LiveView:
    """The live table of a demo run; `on_record` is called on the telemetry thread."""

    def __init__(self, script: DemoScript, policy: str, console: Console, *, enabled: bool):
        self.script = script
        self.policy = policy
        self.console = console
        self.enabled = enabled
        self.status = "starting the robot"
        self._lock = threading.Lock()
        self._latest: Mapping[str, Any] | None = None
        self._latencies: deque[float] = deque(maxlen=ROLLING_FRAMES)
        self._served: Counter[str] = Counter()
        self._fallbacks = 0
        self._frames = 0
        self._serving = "nobody yet"
        self._events: list[str] = []
        self._live: Live | None = None

    def __enter__(self) -> LiveView:
        if self.enabled:
            self._live = Live(
                get_renderable=self.render,
                console=self.console,
                refresh_per_second=LIVE_REFRESH_PER_S,
                transient=False,
            )
            self._live.__enter__()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._live is not None:
            self._live.__exit__(exc_type, exc, tb)
            self._live = None
            if not self.console.is_terminal:
                self.console.line()  # rich leaves the last line open when it is not a terminal

    def on_record(self, rec: Mapping[str, Any]) -> None:
        with self._lock:
            self._latest = rec
            self._frames += 1
            if isinstance(rec.get("latency_s"), (int, float)):
                self._latencies.append(float(rec["latency_s"]))
            dep = answered_by(rec)
            self._served[dep or "robot"] += 1
            self._serving = dep or "robot (computed here)"
            if rec.get("fallback"):
                self._fallbacks += 1
        self.status = "running"

    def event(self, text: str) -> None:
        """A line under the table (a kill, a failover)."""
        with self._lock:
            self._events.append(text)

    def _phase(self, frame: int) -> tuple[int, Phase]:
        for i, phase in enumerate(self.script.phases):
            if frame < phase.end:
                return i, phase
        return len(self.script.phases) - 1, self.script.phases[-1]

    def render(self) -> Group:
        with self._lock:
            rec = self._latest
            frame = int(rec["frame"]) if rec is not None else 0
            rolling = sum(self._latencies) / len(self._latencies) if self._latencies else None
            served = ", ".join(f"{k} {v}" for k, v in sorted(self._served.items()))
            lines = list(self._events)
            frames, fallbacks, serving = self._frames, self._fallbacks, self._serving
        i, phase = self._phase(frame)
        total = self.script.frames
        table = Table(show_header=False, title=f"elasticfog demo: robot-1, policy {self.policy}")
        table.add_column("what", style="bold")
        table.add_column("now")
        table.add_row(
            "phase",
            f"{i + 1}/{len(self.script.phases)} [bold]{phase.name}[/bold] "
            f"(frame {frame - phase.first + 1 if rec else 0}/{phase.frames}; "
            f"{frames}/{total} in all)",
        )
        table.add_row("link (emulated)", link_text(phase.uplink_mbit))
        table.add_row("robot (emulated)", robot_text(phase.slowdown))
        table.add_row("action", str(rec.get("action")) if rec else "-")
        table.add_row(f"latency, last {ROLLING_FRAMES}", ms(rolling))
        table.add_row("serving", serving)
        table.add_row("served so far", f"{served or '-'}; {fallbacks} fallbacks")
        parts: list[Any] = [table]
        parts += [Text(line) for line in lines]
        if self.status != "running":
            parts.append(Text(self.status, style="dim"))
        return Group(*parts)


# -- after the run ---------------------------------------------------------------------------------
def render_run(summary: Mapping[str, Any], reasons: Mapping[str, int], console: Console) -> None:
    """The run's totals and its phases (what `elasticfog demo` prints without --json)."""
    frames = summary["frames"]
    table = Table(
        title=f"elasticfog demo: robot-1, policy {summary['policy']}",
        show_header=False,
        title_justify="left",
    )
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row(
        "frames", f"{frames} asked, {frames - summary['lost']} done, {summary['lost']} lost"
    )
    answered = ", ".join(f"{k} {v}" for k, v in summary["by_deployment"].items()) or "none"
    table.add_row("answered by a deployment", f"{summary['answered']} ({answered})")
    local = frames - summary["lost"] - summary["answered"]
    why = ", ".join(f"{k} {v}" for k, v in reasons.items())
    table.add_row(
        "finished on the robot",
        f"{local} ({summary['fallbacks']} fallbacks{': ' + why if why else ''})",
    )
    table.add_row("actions", ", ".join(f"{k} {v}" for k, v in summary["actions"].items()) or "none")
    table.add_row(
        "latency",
        f"mean {ms(summary['mean_latency_s'])}, p95 {ms(summary['p95_latency_s'])}",
    )
    for fo in summary["failovers"]:
        to = fo["to"] or "nobody (the robot finished every later frame itself)"
        took = f" in {fo['ms']:.0f} ms" if fo["ms"] is not None else ""
        table.add_row("failover", f"killed {fo['from']} at frame {fo['at_frame']} -> {to}{took}")
    if summary.get("tls"):
        table.add_row("links", TLS_TEXT)
    table.add_row("wall time", f"{summary['wall_s']:.1f} s")
    console.print(table)
    console.print(phase_table(summary["phases"]))


def phase_table(phases: Sequence[Mapping[str, Any]]) -> Table:
    """One row per phase: link, robot, main action, latency, bytes per frame, fallbacks."""
    table = Table(title="per phase", title_justify="left")
    for name, justify in (
        ("phase", "left"),
        ("link", "right"),
        ("robot", "right"),
        ("main action", "left"),
        ("mean", "right"),
        ("p95", "right"),
        ("bytes/frame", "right"),
        ("fallbacks", "right"),
    ):
        # The figures never wrap; a long phase name does.
        table.add_column(name, justify=justify, no_wrap=name != "phase")  # type: ignore[arg-type]
    for p in phases:
        share = f" {p['main_share']:.0%}" if p["main_share"] is not None else ""
        table.add_row(
            p["name"],
            link_text(p["uplink_mbit"]),
            f"{p['slowdown']:g}×",
            f"{p['main_action']}{share}",
            ms(p["mean_latency_s"]),
            ms(p["p95_latency_s"]),
            "-" if p["bytes_up"] is None else f"{p['bytes_up']:,}",
            str(p["fallbacks"]),
        )
    return table


def render_compare(result: Mapping[str, Any], console: Console) -> None:
    """`--compare`: per phase, each policy's mean latency and main action, the fastest, and
    whether the demo's policy chose like the fastest fixed policy."""
    runs = result["runs"]
    table = Table(title="--compare: mean latency (main action) per phase", title_justify="left")
    table.add_column("phase")
    for run in runs:
        table.add_column(str(run["policy"]), justify="right", no_wrap=True)
    table.add_column("fastest", no_wrap=True)
    table.add_column(f"{runs[0]['policy']} right?", justify="center", no_wrap=True)
    for i, v in enumerate(result["verdict"]):
        cells = []
        for run in runs:
            p = run["phases"][i]
            cell = f"{ms(p['mean_latency_s'])} {p['main_action']}"
            cells.append(f"[bold]{cell}[/bold]" if run["policy"] == v["fastest"] else cell)
        table.add_row(v["name"], *cells, str(v["fastest"]), "yes" if v["agrees"] else "[red]no")
    lost = ", ".join(f"{r['policy']} {r['lost']}" for r in runs)
    failover = ", ".join(
        f"{r['policy']} {fo['ms']:.0f} ms" if fo["ms"] is not None else f"{r['policy']} n/a"
        for r in runs
        for fo in r["failovers"]
    )
    console.print(table)
    console.print(f"lost: {lost}; failover: {failover or 'none'}", highlight=False)
    if runs and runs[0].get("tls"):
        console.print(TLS_TEXT, highlight=False)
    console.print(f"wall time: {result['wall_s']:.1f} s", highlight=False)


# -- plot ------------------------------------------------------------------------------------------
def save_plot(
    path: Path,
    runs: Sequence[tuple[str, Sequence[Mapping[str, Any]], Mapping[str, Any]]],
    script: DemoScript,
) -> None:
    """Per-frame latency coloured by action, one panel per run (policy, records, summary),
    phase boundaries and the kill marked. matplotlib with the Agg backend (no display)."""
    from common.extras import Extra, require

    matplotlib = require("matplotlib", Extra.PLOTS, "--plot")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = sorted({str(r.get("action")) for _, recs, _ in runs for r in recs}, key=action_order)
    cmap = plt.get_cmap("tab10")
    colours = {label: cmap(i % 10) for i, label in enumerate(labels)}
    fig, axes = plt.subplots(
        len(runs), 1, figsize=(11, 2.6 * len(runs) + 0.6), sharex=True, squeeze=False
    )
    top = max(
        (float(r["latency_s"]) * 1000 for _, recs, _ in runs for r in recs if "latency_s" in r),
        default=1.0,
    )
    for ax, (policy, recs, summary) in zip(axes[:, 0], runs, strict=True):
        for label in labels:
            xs = [r["frame"] for r in recs if str(r.get("action")) == label]
            ys = [float(r["latency_s"]) * 1000 for r in recs if str(r.get("action")) == label]
            if xs:
                ax.scatter(xs, ys, s=6, color=colours[label], label=label)
        for phase in script.phases:
            ax.axvline(phase.first, color="grey", linewidth=0.8, linestyle="--")
            ax.text(
                phase.first + 1,
                top * 1.02,
                f"{phase.name}\n{link_text(phase.uplink_mbit)}, robot {phase.slowdown:g}×",
                fontsize=7,
                va="bottom",
            )
        for fo in summary.get("failovers", []):
            took = f" ({fo['ms']:.0f} ms)" if fo.get("ms") is not None else ""
            ax.axvline(fo["at_frame"], color="red", linewidth=1.0)
            ax.text(
                fo["at_frame"] + 1,
                top * 0.85,
                f"{fo['from']} killed{took}",
                color="red",
                fontsize=7,
            )
        ax.set_ylim(0, top * 1.25)
        ax.set_ylabel(f"{policy}\nlatency (ms)")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, markerscale=2)
    axes[-1, 0].set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
