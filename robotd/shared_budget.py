"""What a robot's services share: one uplink and one CPU. Their decisions take it into account.

Each service's own policy (elastic, a baseline, ...) decides as if it had the robot to itself;
`SharedBudget` follows what every service really uses and, in `joint` mode, lets a service's
decision stand only where the share the others leave it allows it:

- the uplink: the bytes per second each service sends (an EWMA of what its offloaded frames
  sent, over the time between its frames) and the link's rate, measured from every service's
  answered frames (bytes sent over the round trip's network share: the rate a frame saw, so a
  contended link reads slower);
- the CPU: the robot seconds per second each service's frames use, against the robot's cores
  (`os.sched_getaffinity`, or the cgroup's quota where one is set).

A service *ranks* above another by `priority`, then by the tighter deadline. Before a frame is
sent, its offload is priced on the link share the services ranking above it leave (their send
rates subtracted from the link's rate): where the frame's bytes cannot cross that share within
the service's deadline, and the whole model on the robot fits it on the CPU share left, the
service gives way (the frame runs on the robot, action P). The policy then observes that frame
as a P frame it ran, which it is. Independent mode (`joint=False`) measures the same and never
overrides: the services' policies are blind to each other, as separate processes would be.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.config import FleetConfig
from robotd.policies import Decision, Outcome, Policy
from robotd.policies.base import PURE_ROBOT, FrameContext

EWMA = 0.2
# Before this many answered frames the link's rate is not known: nothing gives way yet.
MIN_LINK_SAMPLES = 3
# The share of its deadline a frame's bytes may take on the link share left to it.
LINK_DEADLINE_SHARE = 0.8
MIN_SHARE = 0.05


def robot_cores() -> float:
    """The CPUs this process may use: its affinity, capped by a cgroup v2 or v1 CPU quota."""
    cores = float(len(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else 1.0
    quota = _cgroup_quota()
    return max(min(cores, quota) if quota is not None else cores, MIN_SHARE)


def _cgroup_quota() -> float | None:
    """Cores of this host's CPU cgroup quota (v2's cpu.max, v1's cfs files); None: no quota."""
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        period_us = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota_us / period_us if quota_us > 0 else None


@dataclass
class _Usage:
    """One service's measured use of the robot (EWMAs); `rank` orders who gives way."""

    rank: tuple[int, float]
    deadline_s: float
    send_bps: float = 0.0
    cpu_cores: float = 0.0
    full_s: float | None = None
    last_at: float | None = None
    frames: int = 0
    gave_way: int = 0


class SharedBudget:
    """`SharedBudget(views, joint=True)`: `views` are the robot's services' fleet views
    (`FleetConfig.for_service`), whose priority and deadline rank them."""

    def __init__(
        self,
        views: Mapping[str, FleetConfig],
        *,
        joint: bool = True,
        cores: float | None = None,
        clock: Any = time.monotonic,
    ) -> None:
        self.joint = joint
        self.cores = cores if cores is not None else robot_cores()
        self._clock = clock
        self._lock = threading.Lock()
        self._usage = {
            name: _Usage(
                rank=(-view.service_config.priority, view.deadline_s), deadline_s=view.deadline_s
            )
            for name, view in views.items()
        }
        self.link_bps: float | None = None
        self._link_samples = 0

    def share(self, service: str) -> ServiceShare:
        """What service `service`'s daemon holds: it wraps the service's policy with it."""
        return ServiceShare(self, service)

    # -- measurements --------------------------------------------------------------------------
    def observe(self, service: str, decision: Decision, outcome: Outcome) -> None:
        now = self._clock()
        with self._lock:
            use = self._usage[service]
            gap = None if use.last_at is None else max(now - use.last_at, 1e-3)
            use.last_at = now
            use.frames += 1
            if decision.action == PURE_ROBOT and outcome.prefix_s is not None:
                use.full_s = _ewma(use.full_s, outcome.prefix_s)
            if gap is not None:
                sent = outcome.bytes_up if decision.offloads else 0
                use.send_bps = _ewma(use.send_bps, sent / gap)
                if outcome.cpu_s is not None:
                    use.cpu_cores = _ewma(use.cpu_cores, outcome.cpu_s / gap)
            if decision.offloads and outcome.cloud_s is not None and outcome.bytes_up > 0:
                network_s = outcome.cloud_s - (outcome.cloud_compute_s or 0.0)
                if network_s > 0:
                    self.link_bps = _ewma(self.link_bps, outcome.bytes_up / network_s)
                    self._link_samples += 1

    # -- the decision ------------------------------------------------------------------------
    def gives_way(self, service: str, bytes_up: float, full_s: float) -> bool:
        """Whether `service` should run this frame on the robot instead of sending `bytes_up`
        bytes: they cannot cross the link share the services ranking above it leave within its
        deadline, while the whole model (`full_s` on an idle robot) fits the CPU share left."""
        if not self.joint:
            return False
        with self._lock:
            if self.link_bps is None or self._link_samples < MIN_LINK_SAMPLES:
                return False
            use = self._usage[service]
            above = [u for name, u in self._usage.items() if name != service and u.rank < use.rank]
            link_left = self.link_bps - sum(u.send_bps for u in above)
            cpu_left = self.cores - sum(u.cpu_cores for u in above)
            send_s = bytes_up / max(link_left, MIN_SHARE * self.link_bps)
            robot_s = (use.full_s or full_s) / max(min(cpu_left, 1.0), MIN_SHARE)
            give_way = (
                send_s > LINK_DEADLINE_SHARE * use.deadline_s
                and robot_s < use.deadline_s
                and robot_s < send_s
            )
            if give_way:
                use.gave_way += 1
            return give_way

    def state(self) -> dict[str, Any]:
        """A snapshot for the run summary: the link's rate and each service's use."""
        with self._lock:
            return {
                "joint": self.joint,
                "link_mbit": None if self.link_bps is None else self.link_bps * 8 / 1e6,
                "cores": self.cores,
                "services": {
                    name: {
                        "send_mbit": u.send_bps * 8 / 1e6,
                        "cpu_cores": u.cpu_cores,
                        "gave_way": u.gave_way,
                    }
                    for name, u in self._usage.items()
                },
            }


class ServiceShare:
    """A service's handle on the budget; `wrap(policy)` gives the policy its frame loop runs."""

    def __init__(self, budget: SharedBudget, service: str) -> None:
        self.budget = budget
        self.service = service

    def wrap(self, policy: Policy) -> Policy:
        return SharedPolicy(policy, self)


class SharedPolicy(Policy):
    """The service's own policy, whose offloads give way where the budget says so."""

    def __init__(self, inner: Policy, share: ServiceShare) -> None:
        super().__init__(inner.cuts)
        self.inner = inner
        self.share = share
        self.name = inner.name

    def decide(self, ctx: FrameContext) -> Decision:
        decision = self.inner.decide(ctx)
        if not decision.offloads:
            return decision
        bytes_up = self._bytes_of(decision)
        if self.share.budget.gives_way(self.share.service, bytes_up, self.cuts.full_s):
            return Decision(PURE_ROBOT)
        return decision

    def _bytes_of(self, decision: Decision) -> float:
        learned = getattr(self.inner, "learned_bytes", None)
        if callable(learned):
            found = learned().get(decision.label)
            if found is not None:
                return float(found)
        cuts = self.cuts
        for j, (cut, codec, end) in enumerate(
            zip(cuts.indices, cuts.codecs, cuts.ends, strict=True)
        ):
            if (cut, codec, end) == (int(decision.action), decision.codec, decision.end):
                return float(cuts.bytes[j])
        return float(max(cuts.bytes))

    def observe(self, decision: Decision, outcome: Outcome) -> None:
        self.inner.observe(decision, outcome)
        self.share.budget.observe(self.share.service, decision, outcome)

    def state(self) -> dict[str, Any]:
        return self.inner.state()

    def __getattr__(self, name: str) -> Any:
        # What else the frame loop or the daemon reads of the policy is the inner one's.
        return getattr(self.inner, name)


def _ewma(old: float | None, new: float) -> float:
    return new if old is None else old + EWMA * (new - old)
