"""Split-decision policies: ElasticAction and its baselines behind one interface.

    policy = make_policy("elastic", profile, params={"beta": 0.3}, objective={"latency": 1})
    decision = policy.decide(FrameContext(index=t, entropy=frame_entropy(frame)))
    ... run decision.action (a cut index or "P"), hedged if decision.hedge ...
    policy.observe(decision, Outcome(prefix_s=..., cloud_s=..., bytes_up=..., latency_s=...))

`profile` is the partitioner's profile dict (`{full_ms, cuts: [{index, bytes, prefix_ms,
suffix_ms}, ...]}`); `params` and `objective` are plain dicts from the config file, validated here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from common.errors import UserError
from robotd.policies.base import (
    PURE_ROBOT,
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
from robotd.policies.objective import Objective, PowerModel
from robotd.policies.params import (
    AnsParams,
    ElasticParams,
    NeurosurgeonParams,
    NoParams,
    parse_params,
)

__all__ = [
    "PURE_ROBOT",
    "Action",
    "CutTable",
    "Decision",
    "FrameContext",
    "Objective",
    "Outcome",
    "Policy",
    "PowerModel",
    "action_label",
    "make_policy",
    "policy_names",
]

# Policies the real-time robot daemon can run; `oracle` needs the simulator's ground truth.
REAL_TIME_POLICIES = ("elastic", "ans", "neurosurgeon", "robot", "cloud", "static:K")
SIM_ONLY_POLICIES = ("oracle",)


def policy_names() -> tuple[str, ...]:
    """Every accepted policy spec (`static:K` stands for any cut index K)."""
    return REAL_TIME_POLICIES + SIM_ONLY_POLICIES


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
    if name in ("robot", "cloud", "oracle") or name.startswith("static:"):
        parse_params(NoParams, params, name)
    if name == "robot":
        return FixedPolicy(cuts, PURE_ROBOT, name)
    if name == "cloud":
        return FixedPolicy(cuts, cuts.indices[0], name)
    if name == "oracle":
        return OraclePolicy(cuts)
    if name.startswith("static:"):
        text = name.split(":", 1)[1].strip()
        if not text.isdigit():
            raise UserError(f"policy {spec!r}: static needs a cut index, e.g. static:3")
        return FixedPolicy(cuts, int(text), name)
    raise UserError(f"unknown policy {spec!r}; expected one of {', '.join(policy_names())}")
