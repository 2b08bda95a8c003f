"""Messages between the registry and the daemons: registration, probe, control, routes, RIB views.

Who sends what, and on which key (see docs/keyspace.md):

- `RegisterRequest` -> `RegisterReply`: a cloud or robot daemon announces itself on
  `keys.reg_register`; the registry checks the protocol version, capabilities, service and model
  with `check_registration` and answers with an acceptance or a readable refusal.
- `ProbeRequest` -> `ProbeReply`: anyone (a robot measuring a standby deployment, the registry)
  on `keys.dep_probe`; answered in every state. The request's `padding` and the reply's `echo`
  (of `echo_bytes` bytes) let the prober measure transfer both ways.
- `CtlRequest` -> `CtlReply`: the registry (or an operator, or a test) on `keys.dep_ctl`: put a
  robot in service or standby at an epoch, drain, or set fault injection. Epoch-fenced: a
  deployment refuses a request older than the epoch it already holds for that robot.
- `RouteChange`: published by the registry on `keys.route`, and the reply to a `RerouteRequest`
  (robot -> registry on `keys.reg_reroute`, e.g. after consecutive timeouts).
- `DrainRequest` -> `DrainReply`: a cloud daemon asked to stop (SIGTERM) asks the registry on
  `keys.reg_drain` to move its robots first.
- `RibQuery` -> one of the `*View` messages: the CLI on `keys.rib(...)`; an empty query payload
  means "everything".
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, ClassVar

from common.keys import MACHINE_ROLES, InvalidIdError, Role, validate_id
from common.wire.codec import Message, Struct, register
from common.wire.telemetry import FallbackReason, fallback_reason

# The runtime's protocol (key space + message semantics), distinct from the codec's schema
# version: a registry refuses daemons speaking another protocol with a readable reason.
PROTOCOL_VERSION = 1

# Probe echo sizes above this are refused (the probe is a measurement, not a transfer).
MAX_ECHO_BYTES = 16 * 1024 * 1024


# The `RouteChange.reason` of a robot left without a route because every deployment of its
# service is full (admission control): the robot computes locally until the registry places it.
NO_CAPACITY_REASON = "no_capacity"

# Capability names a daemon may announce.
CAP_INFER = "infer"  # serves the anycast service key
CAP_PROBE = "probe"  # answers probes with echo
CAP_CTL = "ctl"  # obeys service/standby/drain at an epoch
CAP_FAULT_INJECTION = "fault_injection"  # obeys delay/drop/stall
CAP_LOCAL_FALLBACK = "local_fallback"  # a robot that finishes frames itself
CAP_TELEMETRY = "telemetry"  # a robot that publishes per-frame telemetry
CAP_PROBE_REPORTS = "probe_reports"  # a robot that probes standbys and publishes reports

REQUIRED_CAPABILITIES: dict[Role, frozenset[str]] = {
    Role.CLOUD: frozenset({CAP_INFER, CAP_PROBE, CAP_CTL}),
    Role.ROBOT: frozenset({CAP_LOCAL_FALLBACK}),
}


class DeploymentState(str, enum.Enum):
    """A deployment's state for one robot (FogROS2-LS state machine, plus draining)."""

    STANDBY = "standby"
    SERVICE = "service"
    DRAINING = "draining"


class CtlOp(str, enum.Enum):
    """What a `CtlRequest` asks of a deployment."""

    SERVICE = "service"  # declare the robot's service key at `epoch`
    STANDBY = "standby"  # undeclare it (keep the model warm, keep answering probes)
    DRAIN = "drain"  # planned shutdown: stop taking new robots
    FAULT = "fault"  # set fault injection


# -- routes ----------------------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RouteChange(Message):
    """`robot` is now served by `deployment` (None: no deployment, compute locally) from `epoch`
    on. Epochs only grow: a receiver ignores a change older than the one it holds. `at` is the
    registry's wall clock.

    `pool` (extension, `dispatch: round_robin`): every deployment in service for the robot at this
    epoch, `deployment` first; the robot sends each frame to one of them in turn. Empty in an
    anycast fleet (older registries never send it), where `deployment` alone serves."""

    TYPE: ClassVar[str] = "route"
    robot: str
    deployment: str | None
    epoch: int
    reason: str
    at: float
    pool: tuple[str, ...] = ()
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative("epoch")
        self._check_finite("at")
        for member in self.pool:
            try:
                validate_id(member, "pool member")
            except InvalidIdError as exc:
                raise self._invalid("pool", str(exc)) from None
        if self.pool and (self.deployment is None or self.pool[0] != self.deployment):
            raise self._invalid("pool", "must start with the route's deployment")
        if len(set(self.pool)) != len(self.pool):
            raise self._invalid("pool", f"lists a deployment twice: {list(self.pool)}")


# -- registration ----------------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RegisterRequest(Message):
    """A daemon announcing itself. `model_digest` is the sha256 of the model it loaded (None if
    it has not loaded one yet); `software` is its package version, for the event log.
    `max_in_flight`: a robot's offloaded frames in flight at once (pipelining), passed on to the
    deployments that serve it (`CtlRequest.max_in_flight`); absent from older robots."""

    TYPE: ClassVar[str] = "register"
    role: Role
    id: str
    protocol_version: int
    capabilities: tuple[str, ...]
    service: str
    model_digest: str | None = None
    software: str = ""
    max_in_flight: int | None = None

    def __post_init__(self) -> None:
        self._check_ids("id", "service")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise self._invalid("max_in_flight", f"must be at least 1, got {self.max_in_flight}")
        if self.role not in MACHINE_ROLES:
            raise self._invalid("role", f"expected cloud or robot, got {self.role!r}")
        object.__setattr__(self, "role", Role(self.role))  # "cloud" given by hand: the member


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RegisterReply(Message):
    """Acceptance or refusal (`reason` says why, in a sentence). A robot also gets its route."""

    TYPE: ClassVar[str] = "register_reply"
    accepted: bool
    reason: str
    protocol_version: int
    route: RouteChange | None = None


def check_registration(
    request: RegisterRequest,
    *,
    service: str,
    model_digest: str | None = None,
    known_ids: frozenset[str] | None = None,
) -> str | None:
    """The reason to refuse `request`, or None to accept it.

    `service` and `model_digest` are the fleet's; `known_ids` (the machines of fleet.yaml, with
    their role) when the registry only admits configured machines.
    """
    who = f"{request.role} {request.id!r}"
    if request.protocol_version != PROTOCOL_VERSION:
        return (
            f"{who} speaks protocol {request.protocol_version}, this registry speaks "
            f"{PROTOCOL_VERSION}: run the same elasticfog version on every host"
        )
    missing = REQUIRED_CAPABILITIES[request.role] - set(request.capabilities)
    if missing:
        return f"{who} lacks required capabilities: {', '.join(sorted(missing))}"
    if request.service != service:
        return f"{who} serves {request.service!r}, this fleet serves {service!r}"
    if model_digest and request.model_digest and request.model_digest != model_digest:
        return (
            f"{who} loaded model {request.model_digest[:12]}, the fleet's model is "
            f"{model_digest[:12]}: both sides must load the same model"
        )
    if known_ids is not None and request.id not in known_ids:
        return f"{who} is not a machine of this fleet; known: {', '.join(sorted(known_ids))}"
    return None


# -- probe -----------------------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class ProbeRequest(Message):
    """`sender` (a robot or registry id) asks for the deployment's profile; `padding` is carried
    up and `echo_bytes` bytes come back, to measure transfer both ways."""

    TYPE: ClassVar[str] = "probe"
    sender: str
    sent_at: float
    echo_bytes: int = 0
    padding: bytes = b""
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("sender", "service")
        self._check_finite("sent_at")
        self._check_non_negative("echo_bytes")
        if self.echo_bytes > MAX_ECHO_BYTES:
            raise self._invalid("echo_bytes", f"at most {MAX_ECHO_BYTES}, got {self.echo_bytes}")


@dataclass(frozen=True, slots=True, kw_only=True)
class FaultSpec(Struct):
    """Fault injection: `delay_ms` added before each reply, `drop` the probability of not
    answering a request at all, `stall` answering nothing (a frozen host) while still alive."""

    delay_ms: float = 0.0
    drop: float = 0.0
    stall: bool = False

    def __post_init__(self) -> None:
        self._check_finite("delay_ms", "drop")
        self._check_non_negative("delay_ms", "drop")
        if self.drop > 1:
            raise self._invalid("drop", f"is a probability in [0, 1], got {self.drop}")

    @property
    def active(self) -> bool:
        """Whether any fault is injected."""
        return self.delay_ms > 0 or self.drop > 0 or self.stall


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class ProbeReply(Message):
    """A deployment's profile: identity, protocol, what it serves, its state per robot, its load
    (requests queued or running) against its capacity (workers + queue slots), and the echo.
    `epochs` is the epoch it holds per robot, `served` the frames it computed per robot,
    `refused` the requests it refused since it started, by reason (`cloudd.refusals`).
    `providers` are the onnxruntime providers its suffix sessions run on; `providers_fallback`
    is set when they did not get an accelerator the machine asked for and it serves anyway
    (`providers_fallback: allow`)."""

    TYPE: ClassVar[str] = "probe_reply"
    deployment: str
    protocol_version: int
    capabilities: tuple[str, ...]
    service: str
    model_digest: str
    states: dict[str, DeploymentState]
    load: int
    capacity: int
    num_cuts: int = 0
    fault: FaultSpec = field(default_factory=FaultSpec)
    echo: bytes = b""
    epochs: dict[str, int] = field(default_factory=dict)
    served: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    providers: tuple[str, ...] = ()
    providers_fallback: bool = False

    def __post_init__(self) -> None:
        self._check_ids("deployment", "service")
        self._check_non_negative("load", "capacity", "num_cuts")


# -- control ---------------------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class CtlRequest(Message):
    """`service`/`standby` need `robot` and `epoch`; `fault` needs `fault`; `drain` may name a
    robot (drain only that robot) or none (the whole deployment). `max_in_flight` (service and
    standby): the frames the robot keeps in flight, as it announced at registration; the
    deployment admits that many of its requests at once, up to its own cap (None: not known)."""

    TYPE: ClassVar[str] = "ctl"
    op: CtlOp
    robot: str | None = None
    epoch: int = 0
    fault: FaultSpec | None = None
    sender: str = ""
    reason: str = ""
    max_in_flight: int | None = None
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot", "service")
        self._check_non_negative("epoch")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise self._invalid("max_in_flight", f"must be at least 1, got {self.max_in_flight}")
        if self.op in (CtlOp.SERVICE, CtlOp.STANDBY) and self.robot is None:
            raise self._invalid("robot", f"is required for op {self.op.value!r}")
        if self.op is CtlOp.FAULT and self.fault is None:
            raise self._invalid("fault", "is required for op 'fault'")


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class CtlReply(Message):
    """Ack (`ok`) or refusal (`reason` says why, e.g. a stale epoch). `state` is the robot's
    state at the deployment after the request, `epoch` the epoch it now holds."""

    TYPE: ClassVar[str] = "ctl_reply"
    ok: bool
    deployment: str
    op: CtlOp
    robot: str | None = None
    epoch: int = 0
    state: DeploymentState | None = None
    reason: str = ""
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("deployment", "robot", "service")
        self._check_non_negative("epoch")


# -- reroute and drain -----------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RerouteRequest(Message):
    """A robot asks for another deployment: `deployment` at `epoch` failed it (`reason`, the
    fallback reason of its failed frames, with the count of consecutive timeouts). The registry
    answers with a RouteChange or an ErrorReply."""

    TYPE: ClassVar[str] = "reroute"
    robot: str
    deployment: str | None
    epoch: int
    reason: FallbackReason
    consecutive_timeouts: int = 0
    service: str | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "reason", fallback_reason(self.reason))
        except ValueError as exc:
            raise self._invalid("reason", str(exc)) from None
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative("epoch", "consecutive_timeouts")


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class DrainRequest(Message):
    """A deployment about to stop asks the registry to move its robots away first."""

    TYPE: ClassVar[str] = "drain"
    deployment: str
    reason: str = ""

    def __post_init__(self) -> None:
        self._check_ids("deployment")


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class DrainReply(Message):
    """`moved` robots now have another route (or compute locally); `ok` false with a reason when
    the registry could not move them all."""

    TYPE: ClassVar[str] = "drain_reply"
    ok: bool
    moved: tuple[str, ...] = ()
    reason: str = ""


# -- RIB views -------------------------------------------------------------------------------------
@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RibQuery(Message):
    """Optional filters for a RIB view query (an empty payload means no filter). `service`
    (extension): only that service's rows (older registries ignore it and answer them all)."""

    TYPE: ClassVar[str] = "rib_query"
    robot: str | None = None
    deployment: str | None = None
    limit: int | None = None
    service: str | None = None

    def __post_init__(self) -> None:
        self._check_ids("robot", "deployment", "service")
        self._check_non_negative("limit")


@dataclass(frozen=True, slots=True, kw_only=True)
class DeploymentRow(Struct):
    """One deployment as the registry sees it. `last_seen` is the registry's wall clock."""

    id: str
    service: str
    alive: bool
    model_digest: str | None = None
    states: dict[str, DeploymentState] = field(default_factory=dict)
    load: int = 0
    capacity: int = 0
    last_seen: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True, kw_only=True)
class RobotRow(Struct):
    """One robot: its route and why (`reason`, of its last route event), its latency window
    against its bound (`window_stat_s` is the bound's statistic over the last `window_len`
    frames), and the last action its policy chose."""

    id: str
    service: str
    alive: bool
    deployment: str | None = None
    epoch: int = 0
    bound_stat: str = "median"
    bound_s: float | None = None
    window_stat_s: float | None = None
    window_len: int = 0
    deadline_s: float | None = None
    action: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    # Why the robot is where it is: the reason of its last route event ("" before any).
    reason: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class RouteRow(Struct):
    """One robot's current route for one service (`deployment` None: computing locally); `pool`
    (extension): its round-robin pool, the deployment first (empty in an anycast fleet);
    `service` (extension): the service routed (None from older registries: their one service)."""

    robot: str
    deployment: str | None
    epoch: int
    since: float
    reason: str = ""
    pool: tuple[str, ...] = ()
    service: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class EventRow(Struct):
    """One transition in the event log (`seq` increases within a service's log; `at` is the
    registry's wall clock); `service` (extension): whose routing it is about (None from older
    registries)."""

    seq: int
    at: float
    kind: str
    reason: str = ""
    robot: str | None = None
    deployment: str | None = None
    epoch: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    service: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class ProfileRow(Struct):
    """Latency statistics of one robot x deployment pair, over its last `samples` measurements;
    `service` (extension): the service measured (None from older registries)."""

    robot: str
    deployment: str
    samples: int
    median_s: float | None = None
    mean_s: float | None = None
    p95_s: float | None = None
    max_s: float | None = None
    stddev_s: float | None = None
    updated_at: float | None = None
    service: str | None = None


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class DeploymentsView(Message):
    """Reply on `rib/deployments`."""

    TYPE: ClassVar[str] = "rib_deployments"
    rows: tuple[DeploymentRow, ...]
    generated_at: float


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RobotsView(Message):
    """Reply on `rib/robots`."""

    TYPE: ClassVar[str] = "rib_robots"
    rows: tuple[RobotRow, ...]
    generated_at: float


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class RoutesView(Message):
    """Reply on `rib/routes`."""

    TYPE: ClassVar[str] = "rib_routes"
    rows: tuple[RouteRow, ...]
    generated_at: float


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class EventsView(Message):
    """Reply on `rib/events` (oldest first)."""

    TYPE: ClassVar[str] = "rib_events"
    rows: tuple[EventRow, ...]
    generated_at: float


@register
@dataclass(frozen=True, slots=True, kw_only=True)
class ProfilesView(Message):
    """Reply on `rib/profiles`."""

    TYPE: ClassVar[str] = "rib_profiles"
    rows: tuple[ProfileRow, ...]
    generated_at: float


# The reply type of each RIB view, by view name (keys.RIB_VIEWS).
RIB_VIEW_REPLIES: dict[str, type[Message]] = {
    "deployments": DeploymentsView,
    "robots": RobotsView,
    "routes": RoutesView,
    "events": EventsView,
    "profiles": ProfilesView,
}
