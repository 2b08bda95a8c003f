"""Split-decision policies: ElasticAction and its baselines behind one interface.

    policy = make_policy("elastic", profile, params={"beta": 0.3}, objective={"latency": 1})
    decision = policy.decide(FrameContext(index=t, entropy=frame_entropy(frame)))
    ... run decision.action (a cut index or "P") with decision.codec, hedged if decision.hedge ...
    policy.observe(decision, Outcome(prefix_s=..., cloud_s=..., bytes_up=..., latency_s=...))

`profile` is the partitioner's profile dict (`{full_ms, cuts: [{index, bytes, prefix_ms,
suffix_ms, codecs?: [{name, bytes, encode_ms, decode_ms}]}, ...]}`: each (cut, codec) is an
action); `params` and `objective` are plain dicts from the config file, validated here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
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
from robotd.policies.nav_options import OptionParams, nav_option, option_policy, parse_option_spec
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

__all__ = [
    "PURE_ROBOT",
    "RAW_CODEC",
    "Action",
    "CutTable",
    "Decision",
    "FrameContext",
    "Objective",
    "Outcome",
    "Policy",
    "PowerModel",
    "action_label",
    "fixed_action",
    "make_policy",
    "params_model",
    "parse_assignments",
    "policy_names",
    "split_overrides",
]

# Policies the real-time robot daemon can run; `oracle` needs the simulator's ground truth.
REAL_TIME_POLICIES = (
    "elastic",
    "ans",
    "neurosurgeon",
    "robot",
    "cloud",
    "cloud:CODEC",
    "static:K",
    "static:K:CODEC",
)
# Not in REAL_TIME_POLICIES: it builds only on a model that names its `points` cut (zoo:stereo).
NAV_POLICIES = ("option:N", "option:N:CODEC")
SIM_ONLY_POLICIES = ("oracle",)


def policy_names() -> tuple[str, ...]:
    """Every accepted policy spec (`static:K` stands for any cut index K, `CODEC` for any codec
    name the profile offers at that cut, e.g. `cloud:jpeg80`). The navigation options
    (`NAV_POLICIES`: `option:N[:CODEC]`, or `static` with `params: {option: N, codec: C}`) are
    accepted too, on a model that names its `points` cut."""
    return REAL_TIME_POLICIES + SIM_ONLY_POLICIES


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
    if kind == "static":
        if not sep:
            return None  # `static` with `params: {option: N}`: a navigation option
        cut, _, codec = rest.partition(":")
        if not cut.isdigit():
            raise UserError(
                f"policy {spec!r}: static needs a cut index, e.g. static:3 or static:3:int8"
            )
        return FixedAction(int(cut), codec.strip() or RAW_CODEC)
    return None


def params_model(spec: str) -> type[BaseModel]:
    """The pydantic model that validates the params of policy `spec`; UserError if unknown."""
    name = spec.strip().lower() if isinstance(spec, str) else ""
    models: dict[str, type[BaseModel]] = {
        "elastic": ElasticParams,
        "ans": AnsParams,
        "neurosurgeon": NeurosurgeonParams,
    }
    if name in models:
        return models[name]
    if name == "static":
        return OptionParams
    if parse_option_spec(name) is not None:
        return NoParams
    if name in ("robot", "oracle") or fixed_action(name) is not None:
        return NoParams
    raise UserError(f"unknown policy {spec!r}; expected one of {', '.join(policy_names())}")


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
    cuts = CutTable.from_profile(profile)
    goal = Objective.parse(objective)
    if name == "elastic":
        return ElasticPolicy(cuts, parse_params(ElasticParams, params, name), goal, name)
    if name == "ans":
        ans = parse_params(AnsParams, params, name)
        return ElasticPolicy(cuts, elastic_params_for_ans(ans), goal, name)
    if name == "neurosurgeon":
        return NeurosurgeonPolicy(cuts, parse_params(NeurosurgeonParams, params, name), goal)
    option = nav_option(name, params)
    if option is not None:
        return option_policy(option, profile, name)
    fixed = fixed_action(name)
    if name in ("robot", "oracle") or fixed is not None:
        parse_params(NoParams, params, name)
    if name == "robot":
        return FixedPolicy(cuts, PURE_ROBOT, name)
    if name == "oracle":
        return OraclePolicy(cuts)
    if fixed is not None:
        cut = min(cuts.indices) if fixed.cut is None else fixed.cut
        return FixedPolicy(cuts, cut, name, fixed.codec)
    raise UserError(f"unknown policy {spec!r}; expected one of {', '.join(policy_names())}")
