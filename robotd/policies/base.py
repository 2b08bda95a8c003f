"""The policy interface shared by the robot daemon and the simulator.

Each frame the caller asks `Policy.decide(FrameContext)` for a `Decision` (where to cut, and whether
to hedge by also computing the frame locally), runs it, and reports what it measured with
`Policy.observe(decision, Outcome)`. The same calls drive the real-time frame loop and the
trace-driven simulator, so a policy never knows which one it is talking to (except `oracle`, which
needs the simulator's ground truth in `FrameContext.expected_costs`).

An action is a cut index (an `int`: run the prefix up to that cut, send the cut tensors) with the
codec its tensors cross in (`Decision.codec`: `raw`, `fp16`, `int8`, `int8+zstd`, `raw+zstd`,
`jpeg<Q>`, `png`; see `common.wire.tensor_codecs`), or `PURE_ROBOT` (`"P"`: run the whole model on
the robot). Cut 0 sends the model's input (the camera image for image-input models). An action
may also name an end cut (`Decision.end`, segment offload): the cloud runs only the part between
the two cuts and the robot runs the rest from the reply (the nav options of
`robotd.policies.nav_options`).
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal, TypeAlias

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from common.errors import UserError
from common.yaml_files import format_validation_error

PURE_ROBOT: Final = "P"
Action: TypeAlias = int | Literal["P"]

# Results of a classifier are small; used when a profile does not say how big the output is.
DEFAULT_OUTPUT_BYTES: Final = 4096
MS_PER_S: Final = 1000.0
BYTES_PER_MB: Final = 1e6

FloatArray = npt.NDArray[np.float64]


RAW_CODEC: Final = "raw"


def action_label(action: Action, codec: str = RAW_CODEC, end: int | None = None) -> str:
    """The action as a string key, as used in JSON and tables: `"P"`, the cut index for a raw
    crossing (`"3"`), cut and codec (`"0:jpeg80"`); a segment's cuts joined by `-` (`"0-4"`,
    `"0-4:jpeg80"`)."""
    if action == PURE_ROBOT:
        return str(action)
    where = str(action) if end is None else f"{action}-{end}"
    return where if codec == RAW_CODEC else f"{where}:{codec}"


@dataclass(frozen=True, slots=True)
class FrameContext:
    """What a policy knows about a frame before deciding.

    `entropy` is the frame's normalized grey-level entropy in [0, 1] (`robotd.frame_path.entropy`);
    the policy turns it into its key-frame weight σ itself. `expected_costs` is filled by the
    simulator only: the true expected objective cost of each action, in the policy's action order
    (cuts in profile order, then P). Real frames leave it `None`. `keyframe`: a video action
    (`h264`) would send this frame as a keyframe (its stream is new or broken:
    `robotd.frame_path.video_streams`), which costs several times a P-frame's bytes.
    """

    index: int
    entropy: float = 1.0
    expected_costs: Sequence[float] | None = None
    keyframe: bool = False


@dataclass(frozen=True, slots=True)
class Decision:
    """What to do with a frame.

    `hedge`: also finish the frame on the robot (run the local suffix speculatively, starting
    `hedge_after_s` after the request was handed to the uplink) and serve whichever result is
    ready first; the other path's work is stopped, and the cloud reply, when it comes after a
    local result, still feeds the learner. `local_expected` (with `hedge`): the estimates say the
    robot serves this frame best (P) and the request is exploration, so the local run is the
    frame's main path and runs at once at the robot loop's own priority, not as speculative
    low-priority work that the offload's threads would starve. `forced` marks a forced-sampling
    frame and `updating` a frame inside a parameter-update period (both for telemetry).
    `predicted_cost` is the policy's estimate for the chosen action, in objective units (seconds
    for the default latency objective), or None when it has none. `end` (segment offload): the
    cloud stops at this cut and replies with its tensors, the robot runs the suffix from there;
    None: the cloud runs to the model's outputs. A segment is not hedged (its local run would be
    the whole suffix from `action`, racing a reply that still needs the robot's tail).
    """

    action: Action
    hedge: bool = False
    forced: bool = False
    updating: bool = False
    predicted_cost: float | None = None
    hedge_after_s: float = 0.0
    codec: str = RAW_CODEC
    local_expected: bool = False
    end: int | None = None

    def __post_init__(self) -> None:
        if self.end is None:
            return
        if self.action == PURE_ROBOT or not self.end > int(self.action):
            raise ValueError(f"a segment ends after its cut, got cut {self.action}, end {self.end}")
        if self.hedge:
            raise ValueError("a segment action is not hedged")

    @property
    def offloads(self) -> bool:
        """True when the frame is sent to the cloud (any cut, not P)."""
        return self.action != PURE_ROBOT

    @property
    def label(self) -> str:
        """`action_label` of this decision's action, codec and end."""
        return action_label(self.action, self.codec, self.end)


@dataclass(frozen=True, slots=True)
class Outcome:
    """What the robot measured for a frame (all times in seconds).

    - `prefix_s`: robot time of the prefix; for P, of the whole model.
    - `cloud_s`: the cloud-side cost y = upload + cloud compute + return, from sending the cut
      tensors to receiving the reply. None when the cloud did not answer in time (timeout, error,
      busy, no route): the robot then finished locally.
    - `cloud_compute_s`: server-side compute time reported in the reply, when known.
    - `bytes_up`: bytes sent to the cloud.
    - `local_s`: robot time of the local suffix when it ran to completion (hedge or fallback).
    - `latency_s`: end-to-end latency of the frame as served.
    - `waited_s`: how long the robot waited for the cloud before giving up (the deadline), when it
      did not answer.
    - `timed_out`: the cloud did not answer within the deadline (not an early failure such as no
      route or busy): what a congested link looks like.
    - `cpu_s`: the robot's CPU seconds for the frame (process time, every thread: a hedged
      local run included), when measured; the simulator, which models no CPU contention, leaves
      it None.
    - `keyframe`: a video action's frame (`h264`): whether it was sent as a keyframe (its bytes
      are learned apart from P-frames'); None for other actions.
    """

    prefix_s: float | None = None
    cloud_s: float | None = None
    cloud_compute_s: float | None = None
    bytes_up: int = 0
    local_s: float | None = None
    latency_s: float | None = None
    waited_s: float | None = None
    cpu_s: float | None = None
    keyframe: bool | None = None
    timed_out: bool = False


class _CodecModel(BaseModel):
    model_config = ConfigDict(extra="allow")

    name: str = Field(min_length=1, description="Codec of the cut's tensors, e.g. jpeg80.")
    bytes: float = Field(gt=0, description="Median bytes sent with this codec.")
    encode_ms: float = Field(default=0.0, ge=0, description="Encode time on the robot.")
    decode_ms: float = Field(default=0.0, ge=0, description="Decode time in the cloud.")
    key_bytes: float | None = Field(
        default=None,
        gt=0,
        description="A video codec's keyframe bytes (median); `bytes` are its P-frames'. "
        "Absent: `bytes`.",
    )


class _CutModel(BaseModel):
    model_config = ConfigDict(extra="allow")

    index: int = Field(ge=0, description="Cut index; 0 sends the model's inputs.")
    bytes: int = Field(gt=0, description="Bytes crossing the cut (raw).")
    prefix_ms: float = Field(ge=0, description="Prefix time on the profiling host.")
    suffix_ms: float = Field(ge=0, description="Suffix time on the profiling host.")
    codecs: list[_CodecModel] | None = Field(
        default=None,
        description="The codecs this cut may cross in (each an action); absent: raw only.",
    )


class _ProfileModel(BaseModel):
    # A profile is the partitioner's JSON: keep what the policies need, tolerate the rest.
    model_config = ConfigDict(extra="allow")

    full_ms: float = Field(gt=0, description="Whole-model time on the profiling host.")
    output_bytes: int = Field(
        default=DEFAULT_OUTPUT_BYTES, gt=0, description="Bytes of the model's outputs."
    )
    cuts: list[_CutModel] = Field(min_length=1, description="Candidate cuts.")


@dataclass(frozen=True)
class CutTable:
    """The offloading actions of a profile, as arrays in action order: cuts by index, and within
    a cut its codecs in profile order (a profile without codecs gives one raw action per cut).

    Times are seconds on the profiling host: `prefix_s` the robot's part of an action (prefix
    and encode), `suffix_s` the suffix (what the robot runs when it finishes a frame itself,
    from the tensors it still holds), `cloud_s` the cloud's part (decode and suffix); `bytes` is
    what crosses (the median over calibration frames for content-dependent codecs). `ends`
    (empty: none) is each action's end cut, None but for segments (`with_segment`,
    `with_segments`); `returns` the bytes each action's reply brings back (empty: the model's
    `output_bytes` for every action; a segment's: its end cut's tensors, raw) and `tails` the
    robot's part after the reply (empty: none; a segment's: its end cut's suffix, which its
    `prefix_s` includes). Per-frame lookups key on (cut, codec, end) (`positions`), so a
    segment's outcome is never learned as its start cut's. `keys` (empty: `bytes`) is what a
    keyframe of each action sends: a video codec's (`h264`) keyframe, several times its P-frame;
    every other action's is its `bytes`.
    """

    indices: tuple[int, ...]
    codecs: tuple[str, ...]
    bytes: FloatArray
    prefix_s: FloatArray
    suffix_s: FloatArray
    cloud_s: FloatArray
    full_s: float
    output_bytes: int
    ends: tuple[int | None, ...] = ()
    returns: tuple[float, ...] = ()
    tails: tuple[float, ...] = ()
    keys: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.indices)
        if not self.keys:
            object.__setattr__(self, "keys", tuple(float(b) for b in self.bytes))
        for name, empty in (
            ("ends", None),
            ("returns", float(self.output_bytes)),
            ("tails", 0.0),
            ("keys", 0.0),
        ):
            if not getattr(self, name):
                object.__setattr__(self, name, (empty,) * n)
            if len(getattr(self, name)) != n:
                raise ValueError(f"{len(getattr(self, name))} {name} for {n} actions")

    @classmethod
    def from_profile(
        cls, profile: Mapping[str, Any] | CutTable, source: str = "profile"
    ) -> CutTable:
        """Validate a profile dict (the partitioner's JSON); raise UserError naming the field."""
        if isinstance(profile, CutTable):
            return profile
        if not isinstance(profile, Mapping):
            raise UserError(f"{source}: expected a JSON object, got {type(profile).__name__}")
        try:
            model = _ProfileModel.model_validate(dict(profile))
        except ValidationError as exc:
            raise UserError(f"{source}: {format_validation_error(exc, _ProfileModel)}") from None
        cuts = sorted(model.cuts, key=lambda c: c.index)
        seen = [c.index for c in cuts]
        if len(set(seen)) != len(seen):
            dup = next(i for i in seen if seen.count(i) > 1)
            raise UserError(f"{source}: cuts: index {dup} appears more than once")
        rows: list[tuple[int, str, float, float, float, float, float]] = []
        for c in cuts:
            codecs = (
                c.codecs if c.codecs is not None else [_CodecModel(name=RAW_CODEC, bytes=c.bytes)]
            )
            if not codecs:
                raise UserError(f"{source}: cut {c.index}: codecs must not be empty")
            names = [codec.name for codec in codecs]
            if len(set(names)) != len(names):
                raise UserError(f"{source}: cut {c.index}: a codec appears more than once")
            for codec in codecs:
                prefix_ms = c.prefix_ms + codec.encode_ms
                cloud_ms = c.suffix_ms + codec.decode_ms
                key = codec.key_bytes if codec.key_bytes is not None else codec.bytes
                rows.append(
                    (c.index, codec.name, codec.bytes, prefix_ms, c.suffix_ms, cloud_ms, key)
                )
        columns = list(zip(*rows, strict=True))
        return cls(
            indices=tuple(int(i) for i in columns[0]),
            codecs=tuple(str(n) for n in columns[1]),
            bytes=np.array(columns[2], dtype=np.float64),
            prefix_s=np.array(columns[3], dtype=np.float64) / MS_PER_S,
            suffix_s=np.array(columns[4], dtype=np.float64) / MS_PER_S,
            cloud_s=np.array(columns[5], dtype=np.float64) / MS_PER_S,
            full_s=model.full_ms / MS_PER_S,
            output_bytes=model.output_bytes,
            keys=tuple(float(b) for b in columns[6]),
        )

    @property
    def size(self) -> int:
        """Number of offloading actions."""
        return len(self.indices)

    @property
    def has_segments(self) -> bool:
        """True when some action is a segment (the learners then add a feature for the bytes
        coming back, `robotd.policies.segment_actions.action_contexts`)."""
        return any(e is not None for e in self.ends)

    @property
    def returned_bytes(self) -> FloatArray:
        """Bytes each action's reply brings back, in action order."""
        return np.array(self.returns, dtype=np.float64)

    @property
    def tail_s(self) -> FloatArray:
        """The robot's part after each action's reply (a segment's tail; else 0), seconds."""
        return np.array(self.tails, dtype=np.float64)

    @property
    def actions(self) -> tuple[Action, ...]:
        """The cut of every action in the policy order (offloading actions, then P)."""
        return (*self.indices, PURE_ROBOT)

    @property
    def labels(self) -> tuple[str, ...]:
        """`action_label` of every action in the policy order (offloading actions, then P)."""
        rows = zip(self.indices, self.codecs, self.ends, strict=True)
        return (*(action_label(k, c, e) for k, c, e in rows), PURE_ROBOT)

    def position(self, action: Action, codec: str = RAW_CODEC, end: int | None = None) -> int:
        """Column of an action in the policy order (P is last)."""
        if action == PURE_ROBOT:
            return self.size
        key = (int(action), codec, end)
        for j, row in enumerate(zip(self.indices, self.codecs, self.ends, strict=True)):
            if row == key:
                return j
        valid = ", ".join(self.labels[:-1])
        what = f"cut {action}" if end is None else f"the segment from cut {action} to cut {end}"
        what += "" if codec == RAW_CODEC else f" with codec {codec}"
        raise UserError(f"{what} is not in the profile (actions: {valid})")

    def positions(self) -> dict[tuple[int, str, int | None], int]:
        """Column of every offloading action by (cut, codec, end cut), for per-frame lookups
        (`Decision.action`, `.codec`, `.end`); end None for a whole suffix."""
        rows = zip(self.indices, self.codecs, self.ends, strict=True)
        return {(k, c, e): j for j, (k, c, e) in enumerate(rows)}

    def with_segment(self, start: int, end: int, codec: str = RAW_CODEC) -> CutTable:
        """This table with the segment from cut `start` to cut `end` (crossing in `codec`) as
        one more action: the robot runs `start`'s prefix and `end`'s suffix (the tail), the
        cloud the part between and replies with `end`'s tensors (raw); a failed request is
        finished from `start` as for that cut."""
        first = self.position(start, codec)
        last = self.position(end)
        return CutTable(
            indices=(*self.indices, start),
            codecs=(*self.codecs, codec),
            bytes=np.append(self.bytes, self.bytes[first]),
            prefix_s=np.append(self.prefix_s, self.prefix_s[first] + self.suffix_s[last]),
            suffix_s=np.append(self.suffix_s, self.suffix_s[first]),
            cloud_s=np.append(self.cloud_s, max(0.0, self.cloud_s[first] - self.cloud_s[last])),
            full_s=self.full_s,
            output_bytes=self.output_bytes,
            ends=(*self.ends, end),
            returns=(*self.returns, float(self.bytes[last])),
            tails=(*self.tails, float(self.suffix_s[last])),
            keys=(*self.keys, self.keys[first]),
        )

    def with_segments(self, pairs: Sequence[Sequence[int]]) -> CutTable:
        """This table with the segment of every (start, end) pair in `pairs` (a split's
        `segments`), once per codec its start cut crosses in (in table order), after the whole
        suffixes; a pair already present is not added again. UserError for a pair whose cuts
        are not in the table."""
        table = self
        for pair in pairs:
            start, end = (int(c) for c in pair)
            if start not in self.indices or end not in self.indices:
                raise UserError(
                    f"segment from cut {start} to cut {end}: the profile has no such cut "
                    f"(cuts: {', '.join(str(i) for i in sorted(set(self.indices)))})"
                )
            rows = zip(self.indices, self.codecs, self.ends, strict=True)
            for codec in [c for k, c, e in rows if k == start and e is None]:
                if (start, codec, end) not in table.positions():
                    table = table.with_segment(start, end, codec)
        return table

    def undominated(self, slack: float) -> CutTable:
        """The actions that some link speed can make the best, given a robot no faster than the
        cloud (else nothing pays for offloading).

        Action a beats action b at every link speed when a sends no more bytes, leaves no more
        work to the robot and no more work in all (robot plus cloud, on the profiling host) than
        b: the extra work a gives the cloud is then work the slower robot is spared. P is such an
        action too (no bytes, all the work on the robot). Times within `slack` of the whole
        model's time count as equal (profiling noise, and a codec's encode/decode, are smaller
        than what they would keep). A learner that tries a dominated action spends its link on
        it: a 7 MB early-layer crossing ties a 1 Mbit/s uplink up for a minute, to learn what the
        profile already says. The order of the remaining actions is kept; at least one stays.

        Segments stand outside the rule: all are kept, and none prunes a whole suffix. Under
        its premise every segment is beaten by its start cut (the same bytes sent, more back,
        the tail moved to the slower robot, the same work in all), so pruning them would make
        `cuts.segments` a no-op; a segment is there for what the premise excludes, a cloud
        slower than the robot at the tail (loaded, or an accelerator that runs the tail's ops
        badly), which only measurement shows. Nor may a segment prune a whole suffix: the rule
        does not count the bytes coming back (a segment returning the points "beats" the points
        cut), and the whole suffixes kept are then the same with or without segments."""
        tol = slack * self.full_s
        robot = self.prefix_s.tolist()
        work = (self.prefix_s + self.cloud_s).tolist()
        size = self.bytes.tolist()
        whole = [j for j in range(self.size) if self.ends[j] is None]
        rows = {j: (size[j], robot[j], work[j], j) for j in whole}
        rivals = [*rows.values(), (0.0, self.full_s, self.full_s, -1)]  # P, which always stays

        def beats(a: tuple[float, float, float, int], b: tuple[float, float, float, int]) -> bool:
            # The tuple order breaks ties, so of two equal actions exactly one stays.
            close = a[1] <= b[1] + tol and a[2] <= b[2] + tol
            return a[0] <= b[0] and close and (a[3] < 0 or a < b)

        keep = {j for j in whole if not any(beats(a, rows[j]) for a in rivals)}
        if not keep and whole:
            keep = {min(whole, key=lambda j: rows[j])}
        return self.subset([j for j in range(self.size) if j in keep or self.ends[j] is not None])

    def subset(self, columns: Sequence[int]) -> CutTable:
        """The table of the actions in `columns` (in that order)."""
        cols = list(columns)
        return CutTable(
            indices=tuple(self.indices[j] for j in cols),
            codecs=tuple(self.codecs[j] for j in cols),
            bytes=self.bytes[cols],
            prefix_s=self.prefix_s[cols],
            suffix_s=self.suffix_s[cols],
            cloud_s=self.cloud_s[cols],
            full_s=self.full_s,
            output_bytes=self.output_bytes,
            ends=tuple(self.ends[j] for j in cols),
            returns=tuple(self.returns[j] for j in cols),
            tails=tuple(self.tails[j] for j in cols),
            keys=tuple(self.keys[j] for j in cols),
        )

    def decision_at(self, position: int, **fields: Any) -> Decision:
        """A decision for the action in column `position` (its cut, codec and end)."""
        if position == self.size:
            return Decision(PURE_ROBOT, **fields)
        return Decision(
            self.indices[position],
            codec=self.codecs[position],
            end=self.ends[position],
            **fields,
        )


class Policy(abc.ABC):
    """A per-frame split decision: `decide` before the frame, `observe` after it."""

    name: str = "policy"

    def __init__(self, cuts: CutTable) -> None:
        self.cuts = cuts

    @abc.abstractmethod
    def decide(self, ctx: FrameContext) -> Decision:
        """Choose the action (and hedge flag) for this frame."""

    def observe(self, decision: Decision, outcome: Outcome) -> None:  # noqa: B027 - optional hook
        """Learn from what the robot measured; baselines that do not learn ignore it."""

    def state(self) -> dict[str, Any]:
        """A small snapshot for telemetry and debugging (JSON-friendly)."""
        return {"policy": self.name}
