"""Split-decision policies: ElasticAction and its baselines behind one interface.

    policy = make_policy("elastic", profile, params={"beta": 0.3}, objective={"latency": 1})
    decision = policy.decide(FrameContext(index=t, entropy=frame_entropy(frame)))
    ... run decision.action (a cut index or "P") with decision.codec, hedged if decision.hedge ...
    policy.observe(decision, Outcome(prefix_s=..., cloud_s=..., bytes_up=..., latency_s=...))

Every policy is one row of `POLICIES` (its name, the forms of its spec, its parameter model, how
it is built, whether the real-time robot can run it): `policy_kind` finds a spec's row, and
`check_policy` validates a spec and its params before any model loads (the fleet file and the
`--policy` options call it). To add a policy: one `PolicyKind` row.

`profile` is the partitioner's profile dict (`{full_ms, cuts: [{index, bytes, prefix_ms,
suffix_ms, codecs?: [{name, bytes, encode_ms, decode_ms}]}, ...]}`: each (cut, codec) is an
action); `params` and `objective` are plain dicts from the config file, validated here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from common.errors import UserError
from robotd.policies.base import (
    PURE_ROBOT,
    RAW_CODEC,
    Action,
    CutTable,
    Decision,
    FrameContext,
    Outcome,
    Policy,
    action_label,
)
from robotd.policies.baselines import FixedPolicy, NeurosurgeonPolicy, OraclePolicy
from robotd.policies.elastic import ElasticPolicy, elastic_params_for_ans
from robotd.policies.nav_options import (
    OPTION_PREFIX,
    STATIC_KIND,
    OptionParams,
    option_policy,
    parse_option_spec,
)
from robotd.policies.objective import Objective, PowerModel
from robotd.policies.params import (
    AnsParams,
    ElasticParams,
    NeurosurgeonParams,
    NoParams,
    check_override,
    parse_assignments,
    parse_params,
)
from robotd.policies.segment_actions import actions_table

__all__ = [
    "POLICIES",
    "PURE_ROBOT",
    "RAW_CODEC",
    "Action",
    "CutTable",
    "Decision",
    "FrameContext",
    "Objective",
    "Outcome",
    "Policy",
    "PolicyKind",
    "PowerModel",
    "action_label",
    "check_policy",
    "fixed_action",
    "make_policy",
    "params_model",
    "parse_assignments",
    "policy_kind",
    "policy_names",
    "split_overrides",
]


@dataclass(frozen=True)
class FixedAction:
    """The one action of a fixed policy: a cut (None: the profile's lowest) and a codec."""

    cut: int | None
    codec: str


def fixed_action(spec: str) -> FixedAction | None:
    """The action of `cloud[:CODEC]` and `static:K[:CODEC]`; None for every other policy;
    UserError naming the problem for a malformed one. The one parser of these specs."""
    name = spec.strip().lower()
    kind, sep, rest = name.partition(":")
    rest = rest.strip()
    if kind == "cloud":
        if sep and not rest:
            raise UserError(f"policy {spec!r}: cloud: needs a codec, e.g. cloud:jpeg80")
        return FixedAction(None, rest or RAW_CODEC)
    if kind == STATIC_KIND:
        if not sep:
            return None  # `static` with `params: {option: N}`: a navigation option
        cut, _, codec = rest.partition(":")
        if not cut.isdigit():
            raise UserError(
                f"policy {spec!r}: static needs a cut index, e.g. static:3 or static:3:int8"
            )
        return FixedAction(int(cut), codec.strip() or RAW_CODEC)
    return None


# How a policy is built: (its spec, lowercased; the profile; its validated params; the objective).
Build = Callable[[str, Mapping[str, Any] | CutTable, Any, Objective], Policy]


@dataclass(frozen=True)
class PolicyKind:
    """One policy: `name` is the spec's first word (before any ':'), `forms` the specs it takes
    (listed in errors and help), `params` its parameter model for a spec, `check` what parses the
    rest of the spec (None: the bare name only), `build` the policy. `real_time`: the robot
    daemon can run it (`oracle` needs the simulator's ground truth)."""

    name: str
    forms: tuple[str, ...]
    build: Build
    params: Callable[[str], type[BaseModel]] = lambda _spec: NoParams
    check: Callable[[str], object] | None = None
    real_time: bool = True


def _fixed(
    spec: str, profile: Mapping[str, Any] | CutTable, _params: Any, _goal: Objective
) -> Policy:
    cuts = CutTable.from_profile(profile)
    fixed = fixed_action(spec)
    assert fixed is not None  # checked by the row's `check`
    cut = min(cuts.indices) if fixed.cut is None else fixed.cut
    return FixedPolicy(cuts, cut, spec, fixed.codec)


def _static(
    spec: str, profile: Mapping[str, Any] | CutTable, params: Any, goal: Objective
) -> Policy:
    """`static:K[:CODEC]` (a cut), or `static` with `params: {option: N}` (a navigation option)."""
    if spec == STATIC_KIND:
        return option_policy(params, profile, spec)
    return _fixed(spec, profile, params, goal)


def _option(
    spec: str, profile: Mapping[str, Any] | CutTable, _params: Any, _goal: Objective
) -> Policy:
    option = parse_option_spec(spec)
    assert option is not None  # checked by the row's `check`
    return option_policy(option, profile, spec)


def _check_static(spec: str) -> object:
    return spec == STATIC_KIND or fixed_action(spec)


# The policies, by name. A new policy is one row here.
POLICIES: dict[str, PolicyKind] = {
    kind.name: kind
    for kind in (
        PolicyKind(
            "elastic",
            ("elastic",),
            lambda spec, profile, params, goal: ElasticPolicy(
                actions_table(profile, params.segments), params, goal, spec
            ),
            params=lambda _spec: ElasticParams,
        ),
        PolicyKind(
            "ans",
            ("ans",),
            lambda spec, profile, params, goal: ElasticPolicy(
                CutTable.from_profile(profile), elastic_params_for_ans(params), goal, spec
            ),
            params=lambda _spec: AnsParams,
        ),
        PolicyKind(
            "neurosurgeon",
            ("neurosurgeon",),
            lambda spec, profile, params, goal: NeurosurgeonPolicy(
                CutTable.from_profile(profile), params, goal
            ),
            params=lambda _spec: NeurosurgeonParams,
        ),
        PolicyKind(
            "robot",
            ("robot",),
            lambda spec, profile, _params, _goal: FixedPolicy(
                CutTable.from_profile(profile), PURE_ROBOT, spec
            ),
        ),
        PolicyKind("cloud", ("cloud", "cloud:CODEC"), _fixed, check=fixed_action),
        PolicyKind(
            STATIC_KIND,
            ("static:K", "static:K:CODEC"),
            _static,
            # Bare `static` is a navigation option named by its params.
            params=lambda spec: OptionParams if spec == STATIC_KIND else NoParams,
            check=_check_static,
        ),
        # Builds only on a model that names its `points` cut (zoo:stereo).
        PolicyKind(
            OPTION_PREFIX.rstrip(":"),
            ("option:N", "option:N:CODEC"),
            _option,
            check=parse_option_spec,
        ),
        PolicyKind(
            "oracle",
            ("oracle",),
            lambda _spec, profile, _params, _goal: OraclePolicy(CutTable.from_profile(profile)),
            real_time=False,
        ),
    )
}


def policy_names(*, real_time: bool = False) -> tuple[str, ...]:
    """Every accepted policy spec (`static:K` stands for any cut index K, `CODEC` for any codec
    name the profile offers at that cut, e.g. `cloud:jpeg80`); `real_time`: those the robot
    daemon runs. The navigation options (`option:N[:CODEC]`, or `static` with
    `params: {option: N, codec: C}`) build on a model that names its `points` cut."""
    return tuple(
        form for kind in POLICIES.values() if kind.real_time or not real_time for form in kind.forms
    )


def policy_kind(spec: str, *, real_time: bool = False) -> PolicyKind:
    """The row of policy `spec`, its arguments checked; UserError, one line naming the known
    policies, for an unknown one (or, with `real_time`, one the robot cannot run)."""
    name = spec.strip().lower() if isinstance(spec, str) else ""
    word, sep, _ = name.partition(":")
    kind = POLICIES.get(word)
    if kind is None or (sep and kind.check is None) or (real_time and not kind.real_time):
        known = ", ".join(policy_names(real_time=real_time))
        raise UserError(f"unknown policy {spec!r}; expected one of {known}")
    if kind.check is not None:
        kind.check(name)
    return kind


def params_model(spec: str) -> type[BaseModel]:
    """The pydantic model that validates the params of policy `spec`; UserError if unknown."""
    return policy_kind(spec).params(spec.strip().lower())


def check_policy(
    spec: str, params: Mapping[str, Any] | BaseModel | None = None, *, real_time: bool = False
) -> BaseModel:
    """Validate policy `spec` and its `params` without a model (the fleet file and the
    `--policy` options, before anything loads); the validated params. UserError, one line."""
    kind = policy_kind(spec, real_time=real_time)
    name = spec.strip().lower()
    return parse_params(kind.params(name), params, name)


def split_overrides(
    specs: Sequence[str], overrides: Mapping[str, Any], option: str = "--param"
) -> dict[str, dict[str, Any]]:
    """Share parameter overrides (e.g. from `--param KEY=VALUE`) among the policies in `specs`.

    Each policy gets the keys its params model has, validated by that model. With one policy every
    key must be one of its parameters; with several (a comparison), a key may concern only some
    of them (`change_tolerance` is elastic's alone) but must concern at least one. UserError, one
    line naming the option and key, for a key no policy takes or a value that does not fit.
    """
    models = {spec: params_model(spec) for spec in specs}
    if len(specs) == 1:
        spec = specs[0]
        check_override(models[spec], overrides, spec, option)
        return {spec: dict(overrides)}
    for key in overrides:
        if not any(key in model.model_fields for model in models.values()):
            takers = sorted({f for m in models.values() for f in m.model_fields})
            listed = ", ".join(takers) if takers else "none"
            raise UserError(
                f"{option} {key}: none of {', '.join(specs)} has a parameter {key!r} "
                f"(their parameters: {listed})"
            )
    shared: dict[str, dict[str, Any]] = {}
    for spec, model in models.items():
        mine = {k: v for k, v in overrides.items() if k in model.model_fields}
        check_override(model, mine, spec, option)
        shared[spec] = mine
    return shared


def make_policy(
    spec: str,
    profile: Mapping[str, Any] | CutTable,
    params: Mapping[str, Any] | BaseModel | None = None,
    objective: Objective | Mapping[str, Any] | None = None,
) -> Policy:
    """Build the policy named by `spec` for a model profile; UserError for any bad input."""
    if not isinstance(spec, str) or not spec.strip():
        raise UserError(f"policy must be one of {', '.join(policy_names())}")
    name = spec.strip().lower()
    kind = policy_kind(name)
    valid = parse_params(kind.params(name), params, name)
    return kind.build(name, profile, valid, Objective.parse(objective))
