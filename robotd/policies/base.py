"""The policy interface shared by the robot daemon and the simulator.

Each frame the caller asks `Policy.decide(FrameContext)` for a `Decision` (where to cut, and whether
to hedge by also computing the frame locally), runs it, and reports what it measured with
`Policy.observe(decision, Outcome)`. The same calls drive the real-time frame loop and the
trace-driven simulator, so a policy never knows which one it is talking to (except `oracle`, which
needs the simulator's ground truth in `FrameContext.expected_costs`).

An action is a cut index (an `int`: run the prefix up to that cut, send the cut tensors) or
`PURE_ROBOT` (`"P"`: run the whole model on the robot). Cut 0 sends the raw input.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal, TypeAlias

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from common.errors import UserError

PURE_ROBOT: Final = "P"
Action: TypeAlias = int | Literal["P"]

# Results of a classifier are small; used when a profile does not say how big the output is.
DEFAULT_OUTPUT_BYTES: Final = 4096
MS_PER_S: Final = 1000.0
BYTES_PER_MB: Final = 1e6

FloatArray = npt.NDArray[np.float64]


def action_label(action: Action) -> str:
    """The action as a string key (`"P"` or the cut index), as used in JSON and tables."""
    return str(action)


@dataclass(frozen=True, slots=True)
class FrameContext:
    """What a policy knows about a frame before deciding.

    `entropy` is the frame's normalized grey-level entropy in [0, 1] (`robotd.entropy`); the
    policy turns it into its key-frame weight σ itself. `expected_costs` is filled by the simulator
    only: the true expected objective cost of each action, in the policy's action order (cuts in
    profile order, then P). Real frames leave it `None`.
    """

    index: int
    entropy: float = 1.0
    expected_costs: Sequence[float] | None = None


@dataclass(frozen=True, slots=True)
class Decision:
    """What to do with a frame.

    `hedge`: also finish the frame on the robot (run the local suffix speculatively, starting
    `hedge_after_s` after the request was handed to the uplink) and serve whichever result is
    ready first; the other path's work is stopped, and the cloud reply, when it comes after a
    local result, still feeds the learner. `forced` marks a forced-sampling frame and `updating`
    a frame inside a parameter-update period (both for telemetry). `predicted_cost` is the
    policy's estimate for the chosen action, in objective units (seconds for the default latency
    objective), or None when it has none.
    """

    action: Action
    hedge: bool = False
    forced: bool = False
    updating: bool = False
    predicted_cost: float | None = None
    hedge_after_s: float = 0.0

    @property
    def offloads(self) -> bool:
        """True when the frame is sent to the cloud (any cut, not P)."""
        return self.action != PURE_ROBOT


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
    """

    prefix_s: float | None = None
    cloud_s: float | None = None
    cloud_compute_s: float | None = None
    bytes_up: int = 0
    local_s: float | None = None
    latency_s: float | None = None
    waited_s: float | None = None

    @property
    def cloud_answered(self) -> bool:
        """True when the cloud's reply arrived in time."""
        return self.cloud_s is not None


class _CutModel(BaseModel):
    model_config = ConfigDict(extra="allow")

    index: int = Field(ge=0, description="Cut index; 0 sends the model's inputs.")
    bytes: int = Field(gt=0, description="Bytes crossing the cut.")
    prefix_ms: float = Field(ge=0, description="Prefix time on the profiling host.")
    suffix_ms: float = Field(ge=0, description="Suffix time on the profiling host.")


class _ProfileModel(BaseModel):
    # A profile is the partitioner's JSON: keep what the policies need, tolerate the rest.
    model_config = ConfigDict(extra="allow")

    full_ms: float = Field(gt=0, description="Whole-model time on the profiling host.")
    output_bytes: int = Field(
        default=DEFAULT_OUTPUT_BYTES, gt=0, description="Bytes of the model's outputs."
    )
    cuts: list[_CutModel] = Field(min_length=1, description="Candidate cuts.")


def one_line_validation_error(source: str, exc: ValidationError) -> str:
    """The first pydantic error as `source: a.b[2].c: message (got X)`, on one line."""
    err = exc.errors()[0]
    loc = ""
    for part in err["loc"]:
        loc += f"[{part}]" if isinstance(part, int) else (f".{part}" if loc else str(part))
    got = err.get("input")
    shown = "" if isinstance(got, (dict, list)) or got is None else f" (got {got!r})"
    where = f"{loc}: " if loc else ""
    return f"{source}: {where}{err['msg']}{shown}".replace("\n", " ")


@dataclass(frozen=True)
class CutTable:
    """Per-cut costs from a profile, as arrays in cut order (sorted by index).

    Times are seconds on the profiling host; `bytes` is what crosses each cut.
    """

    indices: tuple[int, ...]
    bytes: FloatArray
    prefix_s: FloatArray
    suffix_s: FloatArray
    full_s: float
    output_bytes: int

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
            raise UserError(one_line_validation_error(source, exc)) from None
        cuts = sorted(model.cuts, key=lambda c: c.index)
        seen = [c.index for c in cuts]
        if len(set(seen)) != len(seen):
            dup = next(i for i in seen if seen.count(i) > 1)
            raise UserError(f"{source}: cuts: index {dup} appears more than once")
        return cls(
            indices=tuple(seen),
            bytes=np.array([c.bytes for c in cuts], dtype=np.float64),
            prefix_s=np.array([c.prefix_ms for c in cuts], dtype=np.float64) / MS_PER_S,
            suffix_s=np.array([c.suffix_ms for c in cuts], dtype=np.float64) / MS_PER_S,
            full_s=model.full_ms / MS_PER_S,
            output_bytes=model.output_bytes,
        )

    @property
    def size(self) -> int:
        """Number of cuts (offloading actions)."""
        return len(self.indices)

    @property
    def actions(self) -> tuple[Action, ...]:
        """All actions in the policy order: the cuts, then P."""
        return (*self.indices, PURE_ROBOT)

    def position(self, action: Action) -> int:
        """Column of an action in the policy order (P is last)."""
        if action == PURE_ROBOT:
            return self.size
        try:
            return self.indices.index(int(action))
        except ValueError:
            valid = ", ".join(str(i) for i in self.indices)
            raise UserError(f"cut {action} is not in the profile (cuts: {valid})") from None

    def action_at(self, position: int) -> Action:
        """Inverse of `position`."""
        return PURE_ROBOT if position == self.size else self.indices[position]


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


def finite_or_none(value: float) -> float | None:
    """`value` when finite, else None (for JSON)."""
    return value if math.isfinite(value) else None
