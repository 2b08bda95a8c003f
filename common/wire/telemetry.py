"""What a robot publishes for anyone to read: a record per frame on `keys.tele`, and probe reports
on `keys.tele_probe`.

`TelemetryRecord.to_jsonl()` is the object the robot writes per frame with `--telemetry FILE.jsonl`
(the fields in JSONL_FIELDS, in that order).

Why an offloaded frame was finished on the robot is a closed vocabulary, `FallbackReason`, defined
here once: the robot produces its members, the registry compares them, and nobody reads the words
of a reason. The wire carries the member's string value (the same bytes as the strings older
peers sent), and free text for a person travels apart, in `detail`. A value this version does not
know (a newer robot's) decodes as `FallbackReason.OTHER`, so a registry keeps reading the
records of a robot newer than itself, as it ignores their unknown fields.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, ClassVar

from common.wire.codec import Message, register

# The action label of "pure robot" (run the whole model locally); offloading at cut k is
# action_label(k) ("cut:k"), or action_label(k, codec) ("cut:k:jpeg80") when its tensors cross in
# a codec other than raw; a segment from cut k to cut e (the cloud stops at e, the robot runs the
# rest) is "cut:k-e" or "cut:k-e:<codec>".
ACTION_ROBOT = "P"
_CUT_PREFIX = "cut:"
_RAW = "raw"

# The per-frame JSONL object, in this order (the `--telemetry` contract of `elasticfog robot`).
JSONL_FIELDS = (
    "frame",
    "action",
    "bytes_up",
    "bytes_down",
    "prefix_s",
    "transfer_s",
    "cloud_s",
    "suffix_local_s",
    "latency_s",
    "robot_cpu_s",
    "energy_j",
    "deployment",
    "fallback",
    "reason",
)


class FallbackReason(str, enum.Enum):
    """Why the robot finished an offloaded frame itself (`TelemetryRecord.reason`)."""

    NO_ROUTE = "no_route"  # no deployment serves the robot's service key
    TIMEOUT = "timeout"  # no reply within the deadline (or the emulated uplink needed longer)
    BUSY = "busy"  # the deployment's queue was full
    ERROR = "error"  # an error reply, or a Zenoh error other than a timeout
    DECODE_ERROR = "decode_error"  # a reply that is not a valid message, or not for this frame
    STOPPED = "stopped"  # the robot was asked to stop while waiting
    OTHER = "other"  # a reason this version does not know (sent by a newer robot)

    def __str__(self) -> str:
        # The wire value, in log lines and summaries, as the plain strings were before.
        return self.value

    @classmethod
    def _missing_(cls, value: object) -> FallbackReason | None:
        # Any other string is a newer peer's reason; a value of another type stays an error.
        return cls.OTHER if isinstance(value, str) else None


class ResendReason(str, enum.Enum):
    """Why the robot sent an offloaded frame's query again within its deadline (a move under
    way, or a stale route: docs/registry.md, "A move and the robot's route"; or a video frame
    the deployment could not decode, resent as a keyframe: docs/video.md)."""

    NO_REPLY = "no_reply"  # the query finished without any reply
    NOT_SERVING = "not_serving"  # the only replies were NOT_SERVING (a deployment in standby)
    # The deployment's video decoder could not decode the frame (NEED_KEYFRAME): sent again
    # as a keyframe.
    KEYFRAME = "keyframe"

    def __str__(self) -> str:
        return self.value


def fallback_reason(value: FallbackReason | str) -> FallbackReason:
    """The member for `value` (a member, or its wire string; unknown strings are OTHER);
    ValueError for a value of another type."""
    if isinstance(value, FallbackReason):
        return value
    if not isinstance(value, str):
        raise ValueError(f"expected a fallback reason string, got {type(value).__name__}")
    return FallbackReason(value)


def action_label(cut: int | None, codec: str = _RAW, end: int | None = None) -> str:
    """ "P" for pure robot (cut None), "cut:<k>" for offloading after cut k with raw tensors,
    "cut:<k>:<codec>" with another codec; "cut:<k>-<e>[:<codec>]" for the segment from cut k to
    cut e."""
    if cut is None:
        return ACTION_ROBOT
    if cut < 0:
        raise ValueError(f"cut index must be >= 0, got {cut}")
    if end is not None and end <= cut:
        raise ValueError(f"a segment ends after its cut ({cut}), got {end}")
    where = f"{cut}" if end is None else f"{cut}-{end}"
    return f"{_CUT_PREFIX}{where}" if codec == _RAW else f"{_CUT_PREFIX}{where}:{codec}"


def parse_action_codec(label: str) -> tuple[int | None, str]:
    """(cut index or None for "P", codec) of an action label (a segment's: its first cut);
    ValueError for anything else."""
    return parse_action_segment(label)[::2]


def parse_action_segment(label: str) -> tuple[int | None, int | None, str]:
    """(cut index or None for "P", the segment's end cut or None, codec) of an action label;
    ValueError for anything else."""
    if label == ACTION_ROBOT:
        return None, None, _RAW
    if label.startswith(_CUT_PREFIX):
        where, sep, codec = label[len(_CUT_PREFIX) :].partition(":")
        cut, dash, end = where.partition("-")
        if (
            cut.isdigit()
            and (not dash or (end.isdigit() and int(end) > int(cut)))
            and (codec or not sep)
        ):
            return int(cut), int(end) if dash else None, codec or _RAW
    raise ValueError(
        f"not an action label: {label!r} (expected 'P', 'cut:<k>', 'cut:<k>:<codec>' or "
        "'cut:<k>-<e>[:<codec>]')"
    )


def parse_action(label: str) -> int | None:
    """The cut index of an action label (None for "P"); ValueError for anything else."""
    return parse_action_codec(label)[0]


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class TelemetryRecord(Message):
    """One frame's story. Times are seconds: `prefix_s` on the robot, `transfer_s` the network
    share of the round trip (round trip minus `cloud_s`), `cloud_s` the deployment's queue and
    compute time, `suffix_local_s` the suffix run on the robot when it finished the frame itself,
    `latency_s` end to end. `fallback` is true when the robot finished the frame itself after
    offloading (busy, error, timeout: `reason` says which, `detail` says it for a person);
    `deployment` answered (None if none). `at` is the robot's wall clock when the frame
    completed. `stale`: the frame's result was not applied, a newer frame's had been (a robot
    with frames in flight, `max_in_flight`). `dropped_stale`: frames the source dropped unread
    just before this one, a newer one having arrived (a source fed at its sender's rate, e.g.
    `zenoh`). `resends`: how many times its query was sent again within the deadline because
    it found no serving deployment (0 for a frame answered first time, or not offloaded). A
    `reason` given as its string is read as the wire
    reads it. `keyframe`: for a video frame (`h264`), whether the frame last sent was a
    keyframe (None for any other frame)."""

    TYPE: ClassVar[str] = "telemetry"
    robot: str
    frame: int
    action: str
    bytes_up: int
    bytes_down: int
    prefix_s: float
    transfer_s: float
    cloud_s: float
    suffix_local_s: float
    latency_s: float
    robot_cpu_s: float
    energy_j: float
    deployment: str | None
    fallback: bool
    reason: FallbackReason | None
    detail: str | None = None
    epoch: int = 0
    at: float = 0.0
    stale: bool = False
    dropped_stale: int = 0
    resends: int = 0
    service: str | None = None
    keyframe: bool | None = None

    def __post_init__(self) -> None:
        if self.reason is not None:
            try:
                object.__setattr__(self, "reason", fallback_reason(self.reason))
            except ValueError as exc:
                raise self._invalid("reason", str(exc)) from None
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative(
            "frame", "bytes_up", "bytes_down", "epoch", "dropped_stale", "resends"
        )
        try:
            parse_action(self.action)
        except ValueError as exc:
            raise self._invalid("action", str(exc)) from None

    @property
    def cut(self) -> int | None:
        """The cut of this frame's action (None for pure robot)."""
        return parse_action(self.action)

    def to_jsonl(self) -> dict[str, Any]:
        """The `--telemetry` JSONL object (JSONL_FIELDS, in order), plain JSON values."""
        obj = {name: getattr(self, name) for name in JSONL_FIELDS}
        obj["reason"] = None if self.reason is None else self.reason.value
        return obj


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class ProbeReport(Message):
    """A robot's probe of one deployment: round trip `rtt_s` carrying `up_bytes` and `down_bytes`,
    the deployment's load and capacity from its reply, and `expected_latency_s`, the robot's
    estimate of its per-frame latency through that deployment (None when it cannot tell).
    `ok` false (with `reason`) when the probe got no valid reply in time."""

    TYPE: ClassVar[str] = "probe_report"
    robot: str
    deployment: str
    ok: bool
    at: float
    rtt_s: float | None = None
    up_bytes: int = 0
    down_bytes: int = 0
    load: int | None = None
    capacity: int | None = None
    expected_latency_s: float | None = None
    reason: str | None = None
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative("rtt_s", "up_bytes", "down_bytes", "expected_latency_s")
