"""Baseline policies: robot, cloud, static:K, neurosurgeon and the simulator's oracle.

- `robot`: always P (the whole model on the robot).
- `cloud`: always the lowest cut (cut 0: send the raw input), the node-level full offload.
- `cloud:CODEC`: cut 0 crossing in CODEC (e.g. `cloud:jpeg80`: what a user streaming compressed
  camera frames to one server runs).
- `static:K[:CODEC]`: always cut K (raw, or in CODEC).
- `neurosurgeon`: the profile's costs (scaled by the robot's measured speed, as Neurosurgeon
  profiles the device it runs on) plus a transfer model — RTT and uplink bandwidth as EWMAs of
  recent transfers, cloud speed from the server-reported compute time — and the argmin of the
  predicted cost, with no exploration: once it settles on P it stops seeing transfers.
- `oracle`: the argmin of the true expected costs, which only the simulator knows.

The navigation options (`static` with `params: {option: N, codec: C}`, `option:N[:CODEC]`) are
fixed policies too: `robotd.policies.nav_options`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.errors import UserError
from robotd.policies.base import (
    BYTES_PER_MB,
    PURE_ROBOT,
    RAW_CODEC,
    Action,
    CutTable,
    Decision,
    FrameContext,
    Outcome,
    Policy,
)
from robotd.policies.objective import Objective
from robotd.policies.params import NeurosurgeonParams
from robotd.policies.robotcost import RobotCostModel

BITS_PER_BYTE = 8
MBIT = 1e6
MS_PER_S = 1000.0
# Transfer times are clamped to this before dividing, so a noisy sample cannot divide by zero.
MIN_TRANSFER_S = 1e-4


class FixedPolicy(Policy):
    """Always the same action."""

    def __init__(
        self,
        cuts: CutTable,
        action: Action,
        name: str,
        codec: str = RAW_CODEC,
        end: int | None = None,
    ) -> None:
        super().__init__(cuts)
        # Raises UserError for a cut, codec or segment the profile lacks.
        self._decision = cuts.decision_at(cuts.position(action, codec, end))
        self.name = name

    def decide(self, ctx: FrameContext) -> Decision:
        return self._decision


class OraclePolicy(Policy):
    """The action with the least true expected cost; needs the simulator's ground truth."""

    name = "oracle"

    def decide(self, ctx: FrameContext) -> Decision:
        if ctx.expected_costs is None:
            raise UserError("policy oracle needs the true costs, which only the simulator has")
        best = int(np.argmin(np.asarray(ctx.expected_costs)))
        return self.cuts.decision_at(best, predicted_cost=float(ctx.expected_costs[best]))


class NeurosurgeonPolicy(Policy):
    """Profiled costs plus bandwidth/RTT estimated from recent transfers; no exploration."""

    name = "neurosurgeon"

    def __init__(self, cuts: CutTable, params: NeurosurgeonParams, objective: Objective) -> None:
        super().__init__(cuts)
        self.params = params
        self.objective = objective
        self._robot = RobotCostModel(cuts, objective, params)
        self._position = cuts.positions()
        # Bytes sent per action, followed online like the link (a JPEG's size varies).
        self._bytes = cuts.bytes.copy()
        self.rtt_s = params.rtt_ms / MS_PER_S
        # Seconds per byte: averaging the inverse keeps one slow sample from dominating.
        self.s_per_byte = BITS_PER_BYTE / (params.uplink_mbit * MBIT)
        self.cloud_speedup = params.cloud_speedup
        # Bytes a segment's reply brings back beyond the model's outputs (0 for a whole
        # suffix), taken to cross at the uplink's rate: the transfer model has no downlink.
        self._extra_back = np.maximum(cuts.returned_bytes - cuts.output_bytes, 0.0)

    def predicted_costs(self) -> np.ndarray:
        """Predicted objective cost of every action, cuts then P."""
        cuts = self.cuts
        compute = cuts.cloud_s / self.cloud_speedup
        transfer = self.rtt_s + (self._bytes + self._extra_back) * self.s_per_byte
        cloud = self.objective.wait_rate * (transfer + compute) + self.objective.radio_rate * (
            transfer
        )
        bytes_cost = self.objective.bytes * self._bytes / BYTES_PER_MB
        offload = self._robot.prefix_cost + bytes_cost + cloud
        return np.append(offload, self._robot.full_cost)

    def decide(self, ctx: FrameContext) -> Decision:
        self._robot.tick()
        costs = self.predicted_costs()
        best = int(costs.argmin())
        return self.cuts.decision_at(best, predicted_cost=float(costs[best]))

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        cuts = self.cuts
        if decision.action == PURE_ROBOT:
            self._robot.observe(outcome.prefix_s, cuts.full_s)
            return
        j = self._position[(int(decision.action), decision.codec, decision.end)]
        if outcome.bytes_up > 0:
            self._bytes[j] += self.params.bytes_ewma * (outcome.bytes_up - self._bytes[j])
        robot_s = cuts.prefix_s[j] - (0.0 if outcome.cloud_s is not None else cuts.tails[j])
        self._robot.observe(outcome.prefix_s, float(robot_s))
        if outcome.local_s is not None:
            self._robot.observe(outcome.local_s, float(cuts.suffix_s[j]))
        w = self.params.ewma
        if outcome.cloud_s is not None:
            compute = outcome.cloud_compute_s
            if compute is not None and compute > 0 and cuts.cloud_s[j] > 0:
                speedup = float(cuts.cloud_s[j]) / compute
                self.cloud_speedup += w * (speedup - self.cloud_speedup)
            if compute is None:
                compute = float(cuts.cloud_s[j]) / self.cloud_speedup
            transfer = max(outcome.cloud_s - compute, MIN_TRANSFER_S)
        elif outcome.waited_s is not None:
            transfer = outcome.waited_s  # the transfer took at least this long
        else:
            return
        size = float(self._bytes[j] + self._extra_back[j])
        if size <= self.params.small_transfer_bytes:
            self.rtt_s += w * (transfer - self.rtt_s)
        else:
            sample = max(transfer - self.rtt_s, MIN_TRANSFER_S) / size
            self.s_per_byte += w * (sample - self.s_per_byte)

    def state(self) -> dict[str, Any]:
        return {
            "policy": self.name,
            "rtt_ms": self.rtt_s * MS_PER_S,
            "uplink_mbit": BITS_PER_BYTE / self.s_per_byte / MBIT,
            "cloud_speedup": self.cloud_speedup,
            "robot_speed_ratio": self._robot.ratio,
        }
