"""What a robot's services share: one uplink and one CPU. Their decisions take it into account.

Each service's own policy (elastic, a baseline, ...) decides as if it had the robot to itself;
`SharedBudget` follows what every service really uses and, in `joint` mode, lets a service's
decision stand only where the share the others leave it allows it:

- the uplink: the bytes per second each service sends (its mean bytes per frame over its mean
  time between frames) and the link's rate, measured from every service's answered frames of
  16 KB or more (bytes over the round trip's network share: the rate a frame saw, so a
  contended link reads slower), and bounded at once by a frame that timed out (its bytes did not
  cross in the deadline);
- the CPU: the robot seconds per second each service's frames use, against the robot's cores
  (`os.sched_getaffinity`, capped by the process's own cgroup quota, read again every 2 s).

A service *ranks* above another by `priority`, then by the tighter deadline. Before a frame is
sent, its offload is priced on what the services ranking above it leave: where their sending
plus this service's own (its frame's bytes at its fps) would load the link beyond 70%, or its
frame's bytes cannot cross the share left within 0.8 of its deadline, and the robot's own time
for the frame fits the deadline, the service gives way (the frame runs on the robot, action P)
and keeps giving way for 5 s, then lets one frame through, whose answer measures the link
again. The policy observes a frame that gave way as a P frame it ran, which it is. Independent
mode (`joint=False`) measures the same and never overrides: the services' policies are blind to
each other, as separate processes would be. Measured against each other with `elasticfog
bench services` (docs/experiments.md).
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
# A frame this small crosses in about a round trip whatever the link's rate: its bytes over its
# network time say how far away the deployment is, not how fast the link is.
MIN_LINK_SAMPLE_BYTES = 16 * 1024
# The link's load (what the services ranking above send, and what this one would send at its
# frame rate) beyond which this one gives way: queues grow without bound as the load nears 1.
MAX_LINK_LOAD = 0.7
# A service that gave way keeps giving way this long (its own send rate falls to 0 meanwhile,
# which must not be read as room), then lets one frame through to measure the link again.
GIVE_WAY_HOLD_S = 5.0
CORES_REFRESH_S = 2.0


def robot_cores() -> float:
    """The CPUs this process may use: its affinity, capped by a cgroup v2 or v1 CPU quota."""
    cores = float(len(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else 1.0
    quota = _cgroup_quota()
    return max(min(cores, quota) if quota is not None else cores, MIN_SHARE)


def _cgroup_quota() -> float | None:
    """Cores of this process's CPU cgroup quota (v2's cpu.max, v1's cfs files, in the cgroup
    /proc/self/cgroup names, not the root's); None: no quota."""
    v1, v2 = None, None
    try:
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            _, controllers, path = line.split(":", 2)
            if controllers == "":
                v2 = path
            elif "cpu" in controllers.split(","):
                v1 = path
    except (OSError, ValueError):
        pass
    if v2 is not None:
        try:
            text = (Path("/sys/fs/cgroup") / v2.lstrip("/") / "cpu.max").read_text()
            quota, period = text.split()
            return None if quota == "max" else int(quota) / int(period)
        except (OSError, ValueError):
            pass
    base = Path("/sys/fs/cgroup/cpu") / (v1 or "/").lstrip("/")
    try:
        quota_us = int((base / "cpu.cfs_quota_us").read_text())
        period_us = int((base / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota_us / period_us if quota_us > 0 else None


@dataclass
class _Usage:
    """One service's measured use of the robot (EWMAs); `rank` orders who gives way."""

    rank: tuple[int, float]
    deadline_s: float
    period_s: float | None = None
    """1 / the service's fps (None: as fast as frames complete)."""
    send_bps: float = 0.0
    cpu_cores: float = 0.0
    full_s: float | None = None
    last_at: float | None = None
    gap_s: float | None = None
    sent_bytes: float | None = None
    frames: int = 0
    gave_way: int = 0
    away_until: float = 0.0


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
        self._fixed_cores = cores
        self.cores = cores if cores is not None else robot_cores()
        self._cores_at = clock()
        self._clock = clock
        self._lock = threading.Lock()
        self._usage = {
            name: _Usage(
                rank=(-view.service_config.priority, view.deadline_s),
                deadline_s=view.deadline_s,
                period_s=_period_s(view),
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
                # Rates as averages over averages: one frame observed right after another must
                # not read as a burst of megabytes per second.
                use.gap_s = _ewma(use.gap_s, gap)
                use.sent_bytes = _ewma(use.sent_bytes, outcome.bytes_up if decision.offloads else 0)
                use.send_bps = use.sent_bytes / use.gap_s
                if outcome.cpu_s is not None:
                    use.cpu_cores = _ewma(use.cpu_cores, outcome.cpu_s / gap)
            if decision.offloads and outcome.bytes_up >= MIN_LINK_SAMPLE_BYTES:
                if outcome.cloud_s is not None:
                    network_s = outcome.cloud_s - (outcome.cloud_compute_s or 0.0)
                    if network_s > 0:
                        self.link_bps = _ewma(self.link_bps, outcome.bytes_up / network_s)
                        self._link_samples += 1
                elif outcome.timed_out and outcome.waited_s:
                    # No answer within the deadline (not an early failure: no route, busy):
                    # the link carried less than these bytes in that time, a bound at once (a
                    # link that only hears the frames that made it, and remembers a faster
                    # past, reads faster than it is).
                    bound = outcome.bytes_up / outcome.waited_s
                    self.link_bps = bound if self.link_bps is None else min(self.link_bps, bound)
                    self._link_samples += 1

    # -- the decision ------------------------------------------------------------------------
    def gives_way(self, service: str, bytes_up: float, full_s: float) -> bool:
        """Whether `service` should run this frame on the robot instead of sending `bytes_up`
        bytes: with what the services ranking above it send, and what it would send at its
        frame rate, the link would be loaded past MAX_LINK_LOAD, or its bytes cannot cross the
        share left within its deadline; and the whole model (`full_s` on an idle robot, or as
        measured here) fits its deadline on the CPU share left. Once it gives way it keeps
        doing so for GIVE_WAY_HOLD_S, then lets one frame through to measure the link."""
        if not self.joint:
            return False
        with self._lock:
            if self.link_bps is None or self._link_samples < MIN_LINK_SAMPLES:
                return False
            now = self._clock()
            self._refresh_cores(now)
            use = self._usage[service]
            if now < use.away_until:
                use.gave_way += 1
                return True
            if use.away_until:
                use.away_until = 0.0  # one frame through: its answer measures the link again
                return False
            above = [u for name, u in self._usage.items() if name != service and u.rank < use.rank]
            above_bps = sum(u.send_bps for u in above)
            link_left = self.link_bps - above_bps
            # What it would send at its frame rate, not at the rate it achieves: a service
            # whose frames the link slows down would read as a light one.
            period = min(p for p in (use.period_s, use.gap_s) if p) if use.gap_s else None
            own_bps = bytes_up / period if period else 0.0
            load = (above_bps + own_bps) / self.link_bps
            cpu_left = self.cores - sum(u.cpu_cores for u in above)
            send_s = bytes_up / max(link_left, MIN_SHARE * self.link_bps)
            # A time measured here already ran under the quota and beside the others.
            robot_s = (
                use.full_s
                if use.full_s is not None
                else full_s / max(min(cpu_left, 1.0), MIN_SHARE)
            )
            give_way = (
                load > MAX_LINK_LOAD or send_s > LINK_DEADLINE_SHARE * use.deadline_s
            ) and robot_s < use.deadline_s
            if give_way:
                use.gave_way += 1
                use.away_until = now + GIVE_WAY_HOLD_S
            return give_way

    def _refresh_cores(self, now: float) -> None:
        """The robot's cores, read again now and then (a quota may change while it runs)."""
        if self._fixed_cores is None and now - self._cores_at >= CORES_REFRESH_S:
            self.cores = robot_cores()
            self._cores_at = now

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


def _period_s(view: FleetConfig) -> float | None:
    """1 / the fps a robot of this service's view runs it at (the service's, else a robot's)."""
    fps = view.service_config.fps or next((m.fps for m in view.machines.values() if m.fps), None)
    return 1.0 / fps if fps else None


def _ewma(old: float | None, new: float) -> float:
    return new if old is None else old + EWMA * (new - old)
