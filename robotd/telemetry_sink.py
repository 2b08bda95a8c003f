"""Where the robot's telemetry goes: each served frame's record to `tele/<robot>`, to the
`--telemetry` JSONL file (`robotd.telemetry`) and into the run summary; probe reports to
`tele/<robot>/probe`; with a `/metrics` endpoint, each frame into the robot's Prometheus
metrics too (`robotd.metrics`), counted where the summary counts it.

The sink holds no resource of its own: its publishers and the file are entered into the daemon's
lifecycle as they are made, which releases them at shutdown. Publishing a frame's record is
best effort: a sample Zenoh refuses (e.g. while the session closes) is a debug line, and the
frame still counts in the file and the summary.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import zenoh

from common import keys
from common.daemon import Daemon
from common.wire.telemetry import ProbeReport, TelemetryRecord
from robotd.frame_path.frame import Frame
from robotd.metrics import RobotMetrics
from robotd.telemetry import RunSummary, TelemetryFile, jsonl_object

log = logging.getLogger("robotd")


class TelemetrySink:
    """`TelemetrySink(robot, summary)`; `declare` makes the publishers, `file` is the JSONL
    file once made (None: not made, or not asked for)."""

    def __init__(self, robot: str, summary: RunSummary, service: str | None = None) -> None:
        self.robot = robot
        self.service = service
        self.summary = summary
        self.frames: zenoh.Publisher | None = None
        self.probes: zenoh.Publisher | None = None
        self.file: TelemetryFile | None = None
        self.metrics: RobotMetrics | None = None  # with a /metrics endpoint (`robotd.metrics`)

    def declare(self, owner: Daemon, session: zenoh.Session, fleet: str) -> None:
        """Declare the frame and probe publishers, held by `owner`'s lifecycle."""
        self.frames = owner.hold(
            session.declare_publisher(keys.tele(fleet, self.robot)), "telemetry publisher"
        )
        self.probes = owner.hold(
            session.declare_publisher(keys.tele_probe(fleet, self.robot)), "probe publisher"
        )

    def frame(self, f: Frame, record: TelemetryRecord, *, phase: str | None) -> None:
        """Publish, write and count served frame `f` (its record `record`, its emulation
        phase `phase`), stamped with the sink's service."""
        if self.service is not None:
            record = replace(record, service=self.service)
        if self.frames is not None:
            try:
                self.frames.put(record.to_wire())
            except zenoh.ZError as exc:
                log.debug(
                    "%s: telemetry of frame %d not published: %s", record.robot, record.frame, exc
                )
        if self.file is not None:
            self.file.write(
                jsonl_object(
                    record, entropy=f.entropy, hedged=f.hedged, served_by=f.served_by, phase=phase
                )
            )
        self.summary.add(record, hedged=f.hedged, served_by=f.served_by)
        if self.metrics is not None:
            self.metrics.frame(
                record, f.served_by, f.result.resends if f.result is not None else ()
            )

    def probe(self, report: ProbeReport) -> None:
        """Publish one probe report (the prober's callback)."""
        if self.probes is not None:
            self.probes.put(report.to_wire())
