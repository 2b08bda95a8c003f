"""How the registry reads what robots publish about themselves (telemetry, probe reports).

A publication is decoded strictly (at most `registry.max_request_bytes`, checked on the length
before unpacking) and must be about the robot its key names: a robot publishing on another's key
would poison that robot's measurements. Its `service` must be one of the fleet's (None: a robot of
a one-service fleet, the first service). A bad one is never an error for the publisher (nobody
waits for an answer): it is counted in the refusals and reported once through the daemon's
throttled warning, then dropped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import zenoh

from common import keys
from common.wire import WireError
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.refusals import Refusals
from registry.replies import check_service, check_size

Published = TypeVar("Published", TelemetryRecord, ProbeReport)


class PublicationReader:
    """`read(sample, TelemetryRecord, "telemetry")`: the message, or None once a bad one is
    counted and handed to `on_bad(where, problem)`. `services`: the fleet's (empty: any)."""

    def __init__(
        self,
        refusals: Refusals,
        on_bad: Callable[[str, str], None],
        *,
        max_bytes: int,
        services: Sequence[str] = (),
    ) -> None:
        self.refusals = refusals
        self.max_bytes = max_bytes
        self.services = tuple(services)
        self._on_bad = on_bad

    def read(self, sample: zenoh.Sample, kind: type[Published], what: str) -> Published | None:
        """A robot's publication about itself (the key's robot must be the message's), or None
        once a bad one is reported."""
        key = str(sample.key_expr)
        try:
            data = sample.payload.to_bytes()
            check_size(data, self.max_bytes, what)
            message = kind.from_wire(data, max_bytes=self.max_bytes)
            parts = keys.parse_key(key)
            if parts is None or parts.id != message.robot:
                raise WireError(f"{what} of robot {message.robot!r} published on {key}")
            if self.services:
                check_service(message.service, self.services)
        except WireError as exc:
            self.refusals.count(what, exc.code)
            self._on_bad(f"{what} on {key}", str(exc))
            return None
        return message
