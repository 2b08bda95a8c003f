"""`bench services`'s rows: what a robot's telemetry says of each service, per mode and phase.

A run is one robot process using every service (`--decisions joint` or `independent`), whose
uplink is capped at the uncontended rate and then, while it streams, at the contended one. Its
records (one per frame per service, `--telemetry`) fall into the phases by when each frame
started (`at` - `latency_s`, wall clock): `RunWindows.windows` gives each phase's span. The rows
pool every run of a mode (the rounds alternate the modes, so a drift of the host falls on both),
one per (mode, phase, service), with the sums over the services per (mode, phase) beside them
and the goal's two ratios.

A deadline miss is a frame applied later than its service's deadline (`latency_s` >
`deadline_s`: the robot finished it itself past the deadline, or the answer came late). A frame
is lost when the robot never reported it (numbered below the last frame the service reported:
a run ends with SIGINT, on which the robot finishes its frames in flight and starts no more);
a lost frame counts in the phase its neighbours ran in.
"""

from __future__ import annotations

import statistics
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from .report import fmt, md_table
from .stats import Record, percentile

JOINT, INDEPENDENT = "joint", "independent"
MODES = (JOINT, INDEPENDENT)
UNCONTENDED, CONTENDED = "uncontended", "contended"
PHASES = (UNCONTENDED, CONTENDED)
ROW_KEYS = (
    "mode",
    "phase",
    "service",
    "mean_latency_s",
    "p95_latency_s",
    "deadline_misses",
    "frames",
    "lost",
)
"""The JSON contract's keys of a result row (more follow them)."""
GOAL_CONTENDED_RATIO = 1.3
"""Goal: under the contended uplink, independent decisions' sum of p95 over joint's, at least."""
GOAL_UNCONTENDED_RATIO = 1.05
"""Goal: on the uncontended uplink, joint decisions' sum of p95 over independent's, at most."""
P95 = 95.0


@dataclass(frozen=True)
class ServiceInfo:
    """A service as the bench set it up: what it runs and how it ranks."""

    name: str
    runs: str
    """zoo:NAME, an ONNX file's name or a handler's module:function."""
    kind: str
    """classifier, dense or handler."""
    input_shape: tuple[int, int, int]
    priority: int
    deadline_s: float
    policy: str

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["input_shape"] = list(self.input_shape)
        return out


@dataclass(frozen=True)
class RunWindows:
    """One robot run: its mode and round, its records, the frames asked of each service and
    each phase's span (wall clock, seconds: a frame belongs to the phase it started in)."""

    mode: str
    round: int
    records: list[Record]
    windows: Mapping[str, tuple[float, float]]

    def in_phase(self, service: str, phase: str) -> list[Record]:
        """The service's records of frames that started within the phase."""
        start, stop = self.windows[phase]
        return [
            r for r in self.records if r.get("service") == service and start <= started(r) < stop
        ]

    def lost(self, service: str) -> dict[str, int]:
        """The service's frames never reported, by phase (numbered below the last one it
        reported: a run is stopped by a signal, after which the robot starts no frame): those
        numbered before its first frame of the contended phase are the uncontended phase's."""
        mine = [r for r in self.records if r.get("service") == service]
        seen = {int(r["frame"]) for r in mine}
        change = self.windows[CONTENDED][0]
        later = [int(r["frame"]) for r in mine if started(r) >= change]
        first_contended = min(later, default=max(seen, default=-1) + 1)
        missing = [f for f in range(max(seen, default=-1) + 1) if f not in seen]
        return {
            UNCONTENDED: sum(1 for f in missing if f < first_contended),
            CONTENDED: sum(1 for f in missing if f >= first_contended),
        }

    def to_json(self) -> dict[str, Any]:
        """{"mode", "round", "started_at" (the uncontended phase's start, wall clock, as the
        records' `at`), "windows_s": {phase: [start, stop]} in seconds from it}."""
        origin = self.windows[UNCONTENDED][0]
        return {
            "mode": self.mode,
            "round": self.round,
            "started_at": origin,
            "windows_s": {
                phase: [round(a - origin, 3), round(b - origin, 3)]
                for phase, (a, b) in self.windows.items()
            },
        }


def started(record: Record) -> float:
    """When a frame started (wall clock): its completion less its latency."""
    return float(record["at"]) - float(record["latency_s"])


@dataclass(frozen=True)
class ServiceRow:
    """One (mode, phase, service): the frames of every run of the mode in that phase. Besides
    the contract's figures, where the time went (mean seconds per frame of each stage: the
    robot's own compute `prefix_s` (the whole model for P), the network's share of the round
    trip `transfer_s`, the deployment's `cloud_s`, the robot's local finish `suffix_local_s`),
    the robot CPU and the bytes sent per frame, and the actions taken."""

    mode: str
    phase: str
    service: str
    mean_latency_s: float | None
    p95_latency_s: float | None
    deadline_misses: int
    frames: int
    lost: int
    uplink_mbit: float
    deadline_s: float
    priority: int
    offloaded: int
    """Frames whose result came from a deployment."""
    time_s: dict[str, float | None] = field(default_factory=dict)
    robot_cpu_s: float | None = None
    bytes_up: float | None = None
    actions: dict[str, int] = field(default_factory=dict)
    """Frames per action, most frequent first."""
    fallbacks: dict[str, int] = field(default_factory=dict)
    """Offloaded frames the robot finished itself, per reason (timeout, error, busy...)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class SumRow:
    """One (mode, phase): the sums over the services of their rows' figures."""

    mode: str
    phase: str
    mean_latency_s: float | None
    p95_latency_s: float | None
    deadline_misses: int
    frames: int
    lost: int

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Goal:
    """The goal's ratios of the sums of p95: under contention independent over joint (at least
    GOAL_CONTENDED_RATIO wanted), uncontended joint over independent (at most
    GOAL_UNCONTENDED_RATIO); `met` None where a figure is missing."""

    contended_ratio: float | None
    uncontended_ratio: float | None
    contended_target: float = GOAL_CONTENDED_RATIO
    uncontended_limit: float = GOAL_UNCONTENDED_RATIO

    @property
    def met(self) -> bool | None:
        if self.contended_ratio is None or self.uncontended_ratio is None:
            return None
        return (
            self.contended_ratio >= self.contended_target
            and self.uncontended_ratio <= self.uncontended_limit
        )

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "met": self.met}


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def service_row(
    runs: Sequence[RunWindows],
    mode: str,
    phase: str,
    service: ServiceInfo,
    uplink_mbit: float,
) -> ServiceRow:
    """The row of (mode, phase, service) over the runs of that mode."""
    mine = [run for run in runs if run.mode == mode]
    records = [r for run in mine for r in run.in_phase(service.name, phase)]
    latency = [float(r["latency_s"]) for r in records]

    def stage(key: str) -> float | None:
        return _mean([float(r.get(key) or 0.0) for r in records])

    actions = Counter(str(r["action"]) for r in records)
    fallbacks = Counter(str(r.get("reason")) for r in records if r.get("fallback"))
    return ServiceRow(
        mode=mode,
        phase=phase,
        service=service.name,
        mean_latency_s=_mean(latency),
        p95_latency_s=percentile(latency, P95),
        deadline_misses=sum(1 for x in latency if x > service.deadline_s),
        frames=len(records),
        lost=sum(run.lost(service.name)[phase] for run in mine),
        uplink_mbit=uplink_mbit,
        deadline_s=service.deadline_s,
        priority=service.priority,
        offloaded=sum(1 for r in records if r.get("served_by") == "cloud"),
        time_s={k: stage(k) for k in ("prefix_s", "transfer_s", "cloud_s", "suffix_local_s")},
        robot_cpu_s=stage("robot_cpu_s"),
        bytes_up=stage("bytes_up"),
        actions=dict(actions.most_common()),
        fallbacks=dict(fallbacks.most_common()),
    )


def sum_rows(rows: Sequence[ServiceRow]) -> list[SumRow]:
    """Per (mode, phase), in the rows' order: the services' figures summed (a mean or p95
    is None when a service has none)."""
    out = []
    for mode, phase in dict.fromkeys((r.mode, r.phase) for r in rows):
        mine = [r for r in rows if r.mode == mode and r.phase == phase]
        out.append(
            SumRow(
                mode=mode,
                phase=phase,
                mean_latency_s=_total([r.mean_latency_s for r in mine]),
                p95_latency_s=_total([r.p95_latency_s for r in mine]),
                deadline_misses=sum(r.deadline_misses for r in mine),
                frames=sum(r.frames for r in mine),
                lost=sum(r.lost for r in mine),
            )
        )
    return out


def _total(values: Sequence[float | None]) -> float | None:
    return None if any(v is None for v in values) else sum(v for v in values if v is not None)


def goal(sums: Sequence[SumRow]) -> Goal:
    """The goal's ratios from the sums rows."""

    def p95(mode: str, phase: str) -> float | None:
        return next((s.p95_latency_s for s in sums if s.mode == mode and s.phase == phase), None)

    def ratio(a: float | None, b: float | None) -> float | None:
        return None if a is None or b is None or b <= 0 else a / b

    return Goal(
        contended_ratio=ratio(p95(INDEPENDENT, CONTENDED), p95(JOINT, CONTENDED)),
        uncontended_ratio=ratio(p95(JOINT, UNCONTENDED), p95(INDEPENDENT, UNCONTENDED)),
    )


def build_rows(
    runs: Sequence[RunWindows],
    services: Sequence[ServiceInfo],
    uplinks_mbit: Mapping[str, float],
) -> list[ServiceRow]:
    """Every (mode, phase, service) row, phases outer, then modes, then services."""
    return [
        service_row(runs, mode, phase, service, uplinks_mbit[phase])
        for phase in PHASES
        for mode in MODES
        for service in services
    ]


def markdown(
    rows: Sequence[ServiceRow],
    sums: Sequence[SumRow],
    result_goal: Goal,
    uplinks: Mapping[str, float],
) -> str:
    """Per phase a table of the services (joint / independent in each cell), the sums, the
    goal, and where the time went."""
    out = []
    for phase in PHASES:
        header = [
            "service",
            "priority",
            "deadline (s)",
            "mean (s) joint / indep.",
            "p95 (s) joint / indep.",
            "deadline misses joint / indep.",
            "frames (lost) joint / indep.",
            "main action joint / indep.",
        ]
        table = []
        services = list(dict.fromkeys(r.service for r in rows if r.phase == phase))
        for name in services:
            j = _find(rows, JOINT, phase, name)
            i = _find(rows, INDEPENDENT, phase, name)
            ref = j or i
            assert ref is not None
            table.append(
                [
                    name,
                    str(ref.priority),
                    f"{ref.deadline_s:g}",
                    _pair(j, i, lambda r: fmt(r.mean_latency_s, 3)),
                    _pair(j, i, lambda r: fmt(r.p95_latency_s, 3)),
                    _pair(j, i, lambda r: str(r.deadline_misses)),
                    _pair(j, i, lambda r: f"{r.frames} ({r.lost})"),
                    _pair(j, i, lambda r: _main(r.actions)),
                ]
            )
        sj = next((s for s in sums if s.mode == JOINT and s.phase == phase), None)
        si = next((s for s in sums if s.mode == INDEPENDENT and s.phase == phase), None)
        table.append(
            [
                "**sum**",
                "",
                "",
                _pair(sj, si, lambda s: fmt(s.mean_latency_s, 3)),
                _pair(sj, si, lambda s: fmt(s.p95_latency_s, 3)),
                _pair(sj, si, lambda s: str(s.deadline_misses)),
                _pair(sj, si, lambda s: f"{s.frames} ({s.lost})"),
                "",
            ]
        )
        out.append(f"**{phase} uplink ({uplinks[phase]:g} Mbit/s)**\n\n" + md_table(header, table))
    out.append(_goal_line(result_goal))
    out.append("**where the time goes** (mean s per frame)\n\n" + _time_table(rows))
    return "\n\n".join(out) + "\n"


def _goal_line(g: Goal) -> str:
    c = "n/a" if g.contended_ratio is None else f"{g.contended_ratio:.2f}x"
    u = "n/a" if g.uncontended_ratio is None else f"{g.uncontended_ratio:.2f}x"
    verdict = {True: "met", False: "not met", None: "n/a"}[g.met]
    return (
        f"**goal ({verdict})**: contended, independent's sum of p95 over joint's: {c} "
        f"(wanted >= {g.contended_target:g}x); uncontended, joint's over independent's: {u} "
        f"(wanted <= {g.uncontended_limit:g}x)"
    )


def _time_table(rows: Sequence[ServiceRow]) -> str:
    header = [
        "phase",
        "mode",
        "service",
        "robot compute",
        "network",
        "cloud",
        "local finish",
        "robot CPU",
        "KB up",
        "answered by the cloud",
        "fallbacks",
    ]
    table = [
        [
            r.phase,
            r.mode,
            r.service,
            fmt(r.time_s.get("prefix_s"), 3),
            fmt(r.time_s.get("transfer_s"), 3),
            fmt(r.time_s.get("cloud_s"), 3),
            fmt(r.time_s.get("suffix_local_s"), 3),
            fmt(r.robot_cpu_s, 3),
            "n/a" if r.bytes_up is None else f"{r.bytes_up / 1000:.1f}",
            f"{r.offloaded}/{r.frames}",
            ", ".join(f"{k} {v}" for k, v in r.fallbacks.items()) or "none",
        ]
        for r in rows
    ]
    return md_table(header, table)


def _find(rows: Sequence[ServiceRow], mode: str, phase: str, service: str) -> ServiceRow | None:
    return next(
        (r for r in rows if r.mode == mode and r.phase == phase and r.service == service), None
    )


def _pair(a: Any, b: Any, cell: Any) -> str:
    return f"{'n/a' if a is None else cell(a)} / {'n/a' if b is None else cell(b)}"


def _main(actions: Mapping[str, int]) -> str:
    if not actions:
        return "n/a"
    return next(iter(actions))
