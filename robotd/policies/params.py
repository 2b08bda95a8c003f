"""Parameters of each policy, validated with pydantic (unknown keys are errors).

The config file passes `policy: {kind, params}` and these models check `params`; every field has a
documented default so an empty mapping is always valid. See docs/policies.md for the reasoning
behind the defaults.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from common.errors import UserError
from common.yaml_files import format_validation_error, validation_problem

ForcedKind = Literal["doubling", "every", "off"]


class NoParams(BaseModel):
    """Policies without parameters (robot, cloud, static:K, oracle)."""

    model_config = ConfigDict(extra="forbid")


class RobotCostParams(BaseModel):
    """How the robot-side cost E^c is learned from measured prefix times."""

    model_config = ConfigDict(extra="forbid")

    robot_ewma: float = Field(
        default=0.1,
        gt=0,
        le=1,
        description="Weight of a new measurement in the EWMA of the robot's speed relative to "
        "the profile.",
    )
    robot_change_tolerance: float = Field(
        default=0.3,
        gt=0,
        description="Relative gap between a measured and a predicted robot time that counts as a "
        "change; two such measurements in a row make the estimate jump to them.",
    )
    bytes_ewma: float = Field(
        default=0.2,
        gt=0,
        le=1,
        description="Weight of a frame's bytes sent in the EWMA of its action's bytes (a JPEG's "
        "size follows the content).",
    )


class AnsParams(RobotCostParams):
    """μLinUCB (Autodidactic Neurosurgeon): LinUCB with key-frame weights and forced sampling."""

    beta: float = Field(
        default=1.0,
        ge=0,
        description="Exploration width, in units of the current pure-robot cost: the bonus of an "
        "action is beta·E_P·sqrt((1-σ)·vᵀQ⁻¹v).",
    )
    gamma: float = Field(
        default=1.0,
        gt=0,
        description="Ridge prior: Q starts as gamma·I (context features are O(1)).",
    )
    sigma_key: float = Field(
        default=0.8, ge=0, lt=1, description="σ of key frames (they explore less)."
    )
    sigma_nonkey: float = Field(default=0.2, ge=0, lt=1, description="σ of the other frames.")
    key_entropy: float = Field(
        default=0.8,
        ge=0,
        le=1,
        description="A frame whose normalized grey-level entropy is at least this is a key frame.",
    )
    forced_schedule: ForcedKind = Field(
        default="doubling",
        description="doubling: every ceil(T_e^exponent) frames, T_e doubling from "
        "forced_start_frames; every: every forced_every_frames frames; off: none.",
    )
    forced_start_frames: int = Field(default=200, ge=1, description="First epoch length T_0.")
    # 0.5: a forced sample every 15 frames at first (0.25 forced every 4th). A forced sample is
    # hedged, so it costs little latency itself, but it costs the robot's CPU: on a 0.5-core robot
    # whose best choice was P, sampling every 4th frame made `elastic` 11-14% slower than P
    # (docs/experiments.md, Table I); change detection does not wait for forced frames.
    forced_exponent: float = Field(default=0.5, gt=0, lt=1, description="Interval exponent.")
    forced_every_frames: int = Field(
        default=10, ge=1, description="Interval of the `every` schedule (ElasticROS's I)."
    )
    prune_dominated: bool = Field(
        default=True,
        description="Leave out the actions another action (or P) beats at every link speed: "
        "more bytes and no less robot work (CutTable.undominated); exploring them only ties "
        "the uplink up.",
    )

    @model_validator(mode="after")
    def _sigma_order(self) -> AnsParams:
        if self.sigma_nonkey > self.sigma_key:
            raise ValueError(
                f"sigma_nonkey ({self.sigma_nonkey}) must be <= sigma_key ({self.sigma_key})"
            )
        return self


class ElasticParams(AnsParams):
    """ElasticAction: μLinUCB plus change detection, direction restriction and hedging."""

    segments: bool = Field(
        default=True,
        description="On a split made with segments (fleet `cuts.segments`), also learn each "
        "segment (cut_in, cut_out, codec) as an action; false: whole suffixes only.",
    )
    change_detection: bool = Field(
        default=True, description="Start a parameter-update period when predictions stop fitting."
    )
    change_tolerance: float = Field(
        default=0.25,
        gt=0,
        description="Relative residual |y-ŷ|/ŷ beyond which a prediction misses; within it, it "
        "fits.",
    )
    known_samples: int = Field(
        default=16,
        ge=1,
        description="Misses count only on actions whose prediction rests on about this many "
        "observations (confidence width vᵀQ⁻¹v <= 1/known_samples).",
    )
    change_frames: int = Field(
        default=3, ge=1, description="Misses in a row (same sign) that start an update period."
    )
    fit_frames: int = Field(
        default=4,
        ge=1,
        description="Fitting predictions in a row that end an update period; it also ends when "
        "the mean relative residual of the last fit_frames is within half of change_tolerance.",
    )
    max_update_frames: int = Field(
        default=200, ge=1, description="An update period ends after at most this many frames."
    )
    direction_restriction: bool = Field(
        default=True,
        description="During an update period, slower than predicted → only actions sending no "
        "more data than the one that missed (and P); faster → only actions sending at least as "
        "much.",
    )
    hedge: bool = Field(
        default=True,
        description="Also compute exploring frames locally (deferred while the cloud is "
        "expected first) and serve the faster path.",
    )
    confirm_misses: bool = Field(
        default=True,
        description="After a miss, make the next frame a forced (offloading) frame instead of "
        "waiting for the next scheduled one, so a change is confirmed in change_frames frames.",
    )
    takeover_margin: float = Field(
        default=0.2,
        ge=0,
        lt=1,
        description="An offloading action whose last takeover_samples observations each cost "
        "less than (1 - margin) of the current choice's estimate is taken up (an update period "
        "on its evidence), however few samples the model has of it; it is sampled on the next "
        "frames to confirm. 0: off.",
    )
    takeover_samples: int = Field(
        default=2,
        ge=1,
        description="Observations in a row of one action beating the current choice by "
        "takeover_margin that take it up.",
    )
    robot_probe_frames: int = Field(
        default=10,
        ge=0,
        description="When the robot has not timed a local run for this many frames, hedge the "
        "next offloaded frame (without hedging: serve it on the robot, the interval doubling up "
        "to 4x while the estimate holds) so its robot cost stays fresh (0: never).",
    )


class NeurosurgeonParams(RobotCostParams):
    """Neurosurgeon: profiled costs and a transfer model estimated from recent transfers."""

    uplink_mbit: float = Field(default=10.0, gt=0, description="Initial uplink estimate, Mbit/s.")
    rtt_ms: float = Field(default=20.0, ge=0, description="Initial round-trip estimate, ms.")
    cloud_speedup: float = Field(
        default=4.0, gt=0, description="Initial cloud speed relative to the profiling host."
    )
    ewma: float = Field(
        default=0.3, gt=0, le=1, description="Weight of a new transfer in the estimates."
    )
    small_transfer_bytes: int = Field(
        default=16384,
        ge=0,
        description="Transfers up to this size update the RTT estimate; larger ones the bandwidth.",
    )


P = TypeVar("P", bound=BaseModel)


def parse_params(model: type[P], params: Mapping[str, Any] | BaseModel | None, policy: str) -> P:
    """Validate `params` for `policy`; UserError naming the bad key on failure."""
    if params is None:
        return model()
    if isinstance(params, model):
        return params
    if isinstance(params, BaseModel):
        params = params.model_dump()
    if not isinstance(params, Mapping):
        raise UserError(f"policy {policy}: params must be a mapping, got {type(params).__name__}")
    try:
        return model.model_validate(dict(params))
    except ValidationError as exc:
        raise UserError(f"policy {policy} params: {format_validation_error(exc, model)}") from None


def parse_assignments(items: Sequence[str], option: str = "--param") -> dict[str, str]:
    """`["beta=0.5", "hedge=false"]` → `{"beta": "0.5", "hedge": "false"}` (a repeated key: the
    last one wins); UserError for an item that is not KEY=VALUE. Values stay strings: the params
    model converts them (`0.5` to a float, `false` to a bool) and rejects what does not fit."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key or not value.strip():
            raise UserError(f"{option} {item!r}: expected KEY=VALUE, e.g. {option} beta=0.5")
        out[key] = value.strip()
    return out


def check_override(
    model: type[BaseModel], overrides: Mapping[str, Any], policy: str, option: str = "--param"
) -> None:
    """UserError naming the option and key when `overrides` do not fit `model`."""
    fields = model.model_fields
    for key in overrides:
        if key not in fields:
            raise UserError(f"{option} {key}: {_no_such_parameter(model, key, policy)}")
    try:
        model.model_validate(dict(overrides))
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        loc = err["loc"]
        if loc and loc[0] in overrides:
            head = f"{option} {loc[0]}={overrides[str(loc[0])]}"
        else:
            head = f"{option} ({', '.join(f'{k}={v}' for k, v in overrides.items())})"
        problem = validation_problem(err, model, with_input=False)  # the head shows the value
        raise UserError(f"{head}: policy {policy}: {problem}") from None


def _no_such_parameter(model: type[BaseModel], key: str, policy: str) -> str:
    names = sorted(model.model_fields)
    if not names:
        return f"policy {policy} takes no parameters"
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"did you mean {close[0]}?" if close else f"its parameters: {', '.join(names)}"
    return f"policy {policy} has no parameter {key!r} ({hint})"
