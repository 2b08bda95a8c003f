"""`FallbackReason` on the wire: each member encodes to the string older peers sent (the same
bytes), decodes back to its member, a newer peer's unknown reason decodes as OTHER instead of
failing the whole record, and a reason of another type is a named decode error.
"""

from __future__ import annotations

import json
from typing import Any

import pytest

from common.wire import SCHEMA_VERSION, InvalidValue, decode, encode_raw
from common.wire.registry import RerouteRequest
from common.wire.telemetry import FallbackReason, TelemetryRecord

# The strings the robot put on the wire before the reasons were an Enum.
LEGACY_VALUES = ("no_route", "timeout", "busy", "error", "decode_error", "stopped")


def fields(**overrides: Any) -> dict[str, Any]:
    """A fallback TelemetryRecord's fields, as the constructor and the wire map take them."""
    base: dict[str, Any] = {
        "robot": "robot-1",
        "frame": 3,
        "action": "cut:1",
        "bytes_up": 100,
        "bytes_down": 0,
        "prefix_s": 0.001,
        "transfer_s": 0.2,
        "cloud_s": 0.0,
        "suffix_local_s": 0.01,
        "latency_s": 0.21,
        "robot_cpu_s": 0.01,
        "energy_j": 0.0,
        "deployment": None,
        "fallback": True,
        "reason": "timeout",
        "detail": "no reply within 0.200 s",
        "epoch": 2,
        "at": 5.0,
        "stale": False,
        "dropped_stale": 0,
        "resends": 0,
        "service": None,
        "keyframe": None,
    }
    return {**base, **overrides}


def wire(**overrides: Any) -> bytes:
    """A telemetry record's bytes, built by hand the way any sender (old or new) may build it."""
    return encode_raw({"v": SCHEMA_VERSION, "t": TelemetryRecord.TYPE, **fields(**overrides)})


def test_the_values_are_the_strings_older_peers_sent() -> None:
    assert [m.value for m in FallbackReason if m is not FallbackReason.OTHER] == list(LEGACY_VALUES)


@pytest.mark.parametrize("value", LEGACY_VALUES)
def test_a_member_encodes_to_the_same_bytes_as_its_string(value: str) -> None:
    record = TelemetryRecord(**fields(reason=FallbackReason(value)))
    assert record.to_wire() == wire(reason=value)


@pytest.mark.parametrize("member", list(FallbackReason))
def test_each_reason_decodes_to_its_member(member: FallbackReason) -> None:
    record = decode(wire(reason=member.value), expect=TelemetryRecord)
    assert record.reason is member
    assert record.detail == "no reply within 0.200 s"


def test_a_newer_peers_reason_decodes_as_other() -> None:
    """Forward compatibility: an unknown reason (and an unknown field) from a newer robot still
    gives a record; only the reason is read as OTHER."""
    record = decode(wire(reason="thermal_throttle", future_field=1), expect=TelemetryRecord)
    assert record.reason is FallbackReason.OTHER
    assert (record.robot, record.frame, record.fallback) == ("robot-1", 3, True)


@pytest.mark.parametrize("bad", [7, True, ["timeout"], {"timeout": 1}])
def test_a_reason_of_another_type_is_a_named_decode_error(bad: object) -> None:
    with pytest.raises(InvalidValue, match=r"telemetry\.reason"):
        decode(wire(reason=bad), expect=TelemetryRecord)


def test_an_older_peers_record_without_detail_decodes() -> None:
    body = fields()
    del body["detail"]
    data = encode_raw({"v": SCHEMA_VERSION, "t": TelemetryRecord.TYPE, **body})
    record = decode(data, expect=TelemetryRecord)
    assert (record.reason, record.detail) == (FallbackReason.TIMEOUT, None)


def test_an_older_peers_record_without_resends_decodes_with_none() -> None:
    body = fields()
    del body["resends"]
    data = encode_raw({"v": SCHEMA_VERSION, "t": TelemetryRecord.TYPE, **body})
    assert decode(data, expect=TelemetryRecord).resends == 0


def test_a_reason_given_as_its_string_is_read_as_the_wire_reads_it() -> None:
    assert TelemetryRecord(**fields(reason="busy")).reason is FallbackReason.BUSY
    assert TelemetryRecord(**fields(reason="newer")).reason is FallbackReason.OTHER
    assert TelemetryRecord(**fields(reason=None, fallback=False)).reason is None


def test_jsonl_and_log_lines_show_the_plain_value() -> None:
    record = TelemetryRecord(**fields(reason=FallbackReason.NO_ROUTE))
    line = json.loads(json.dumps(record.to_jsonl()))
    assert line["reason"] == "no_route" and type(record.to_jsonl()["reason"]) is str
    assert f"{FallbackReason.NO_ROUTE}" == str(FallbackReason.NO_ROUTE) == "no_route"


def test_a_reroute_request_carries_the_member() -> None:
    request = RerouteRequest(
        robot="robot-1",
        deployment="edge-1",
        epoch=4,
        reason=FallbackReason.NO_ROUTE,
        consecutive_timeouts=3,
    )
    got = decode(request.to_wire(), expect=RerouteRequest)
    assert got == request and got.reason is FallbackReason.NO_ROUTE
