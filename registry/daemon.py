"""The registry daemon: the RIB, the scheduler and the switch protocol wired to Zenoh.

Lifecycle (common.daemon.Daemon): `startup` opens the RIB (routes, epochs and profiles come back
from sqlite; liveness flags are reset), opens the session (a router listening on
`registry.listen`, so a fresh host needs nothing else; data never flows through it: peers link
to each other directly), declares the queryables and subscribers, seeds membership from a
liveliness get and follows it with a subscriber, and declares `alive/registry/<id>` last, once
it is ready. `main_loop` is the control loop. `shutdown` undoes all of it in reverse order.

Threads. Zenoh callbacks stay short: liveliness changes, drain and reroute requests are queued
for the control loop; telemetry and probe reports only update the latency windows (under a
lock); the read-only views and `reg/register` are answered on the callback thread from the RIB.
Probing a deployment (registration, and a load refresh every few seconds) runs on a small pool
and queues its result. The control loop (the main thread) is the only one that decides and
switches: it handles queued events at once and runs the scheduler every `tick_s` (~100 ms).

Decisions. A robot with no live route gets one: its restored route if that deployment is alive
(re-asserted at the same epoch, so a cloud daemon restarted meanwhile declares the key again),
else initial_policy's service machine if alive, else the scheduler's choice. A deployment whose
token disappears, or a robot reporting `timeout_count` consecutive timeouts (in telemetry or by a
`reg/reroute` request), is handled at once; bound violations and improvements wait out the
scheduler's hysteresis. After a restart, a route whose deployment has not reconnected yet is left
alone for `restore_grace_s` (peers retry their connection to the router every few seconds).

Registration. A new cloud token is probed: protocol version, capabilities, service and model
digest are checked with `check_registration`; a mismatch is refused with an event and a log line
naming the deployment and the reason, and nothing is ever routed to it. A deployment found
serving a robot that the RIB routes elsewhere is put back in standby (anycast repair).

Measures. Telemetry and probe reports feed the same measure, the remote part of a frame: a frame
answered by a deployment counts `transfer_s + cloud_s`; a frame that timed out counts the deadline
(at least), and its deployment's consecutive timeouts grow; a probe report counts the robot's
`expected_latency_s` when it gives one, else the probe's round trip. Windows are persisted every
`PROFILE_SAVE_INTERVAL_S` and at shutdown, not on every sample.

Bad input to any queryable (garbage, an unknown schema version, a wrong message type, a malformed
request) gets an `ErrorReply` naming the problem; a bad publication is logged (once in a while)
and dropped. The daemon keeps serving either way.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from common import keys
from common.config import FleetConfig
from common.daemon import Daemon
from common.errors import UserError
from common.models import file_digest
from common.session import open_session, zenoh_error_text
from common.wire import ErrorCode, ErrorReply, Message, WireError, decode, error_reply
from common.wire import registry as msg
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.latency import LatencyBound, LatencyWindows, Source, Stat, WindowKey
from registry.rib import EventKind, Rib
from registry.scheduler import (
    Decision,
    DeploymentView,
    Reason,
    RobotView,
    Scheduler,
    SchedulerParams,
)
from registry.switch import (
    CTL_TIMEOUT_S,
    Outcome,
    Switcher,
    SwitchResult,
    TransportError,
    carry_out,
)
from registry.transport import ZenohTransport

log = logging.getLogger(__name__)

SCHEDULER_TICK_S = 0.1
PROFILE_SAVE_INTERVAL_S = 5.0
LOAD_REFRESH_INTERVAL_S = 2.0
# Peers retry their connection to a restarted router with a back-off of up to 4 s (zenoh's
# default): until then a restored route's deployment is "not seen yet", not "lost".
RESTORE_GRACE_S = 5.0
PROBE_TIMEOUT_S = 0.5
REGISTRATION_ATTEMPTS = 3
PROBE_WORKERS = 2
# Requests to the registry, telemetry and probe reports are small; bigger ones are refused before
# unpacking.
MAX_REQUEST_BYTES = 64 * 1024
DEFAULT_EVENTS_LIMIT = 100
MAX_EVENTS_LIMIT = 10_000
BAD_INPUT_LOG_INTERVAL_S = 10.0
BAD_INPUT_LOG_KEYS = 1000
# Fallback reasons (telemetry `reason`) that mean the deployment did not answer in time, and
# those that mean nobody serves the robot's key at all: both count as consecutive failures of the
# route (only the first are latency samples).
TIMEOUT_WORDS = ("timeout", "deadline", "no reply")
NO_SERVER_WORDS = ("no_route", "no route")
STOPPING_REASON = "the registry is stopping"


# -- events for the control loop ---------------------------------------------------------------
@dataclass(frozen=True)
class _Membership:
    role: str
    id: str
    alive: bool
    seed: bool = False  # from the liveliness get at start (older than any subscriber event)


@dataclass(frozen=True)
class _Probed:
    deployment: str
    reply: msg.ProbeReply | None
    error: str
    refresh: bool


@dataclass(frozen=True)
class _Evaluate:
    robot: str


@dataclass(frozen=True)
class _Request:
    message: Message
    query: zenoh.Query
    key: str  # the queryable's own key: replies go there (the query's may hold wildcards)


_Event = _Membership | _Probed | _Evaluate | _Request


@dataclass
class _Registration:
    state: str  # "pending", "accepted" or "refused"
    reason: str = ""
    retry: bool = False  # refused for want of an answer: probed again now and then


def fleet_model_digest(cfg: FleetConfig) -> str | None:
    """The fleet model's sha256 when the registry can tell without building anything: a model
    file present on this host. None for a zoo model (the registry never exports one): the first
    deployment accepted then sets the reference the others must match."""
    path = cfg.model_path
    if path is None or not path.is_file():
        return None
    try:
        return file_digest(path)
    except OSError as exc:
        log.warning("cannot read the model %s to check digests: %s", path, exc)
        return None


def _is_timeout(reason: str | None) -> bool:
    text = (reason or "").lower()
    return any(word in text for word in TIMEOUT_WORDS)


def _is_unserved(reason: str | None) -> bool:
    text = (reason or "").lower()
    return any(word in text for word in NO_SERVER_WORDS)


class RegistryDaemon(Daemon):
    """`elasticfog registry`: see the module docstring."""

    name = "registry"

    def __init__(
        self,
        cfg: FleetConfig,
        *,
        db_path: str | Path | None = None,
        params: SchedulerParams | None = None,
        tick_s: float = SCHEDULER_TICK_S,
        ctl_timeout_s: float = CTL_TIMEOUT_S,
        restore_grace_s: float = RESTORE_GRACE_S,
        profile_save_interval_s: float = PROFILE_SAVE_INTERVAL_S,
        load_refresh_interval_s: float = LOAD_REFRESH_INTERVAL_S,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.fleet = cfg.fleet
        self.id = cfg.registry.id
        self.service = cfg.service
        self.db_path = Path(db_path) if db_path is not None else cfg.db_path
        lb = cfg.latency_bound
        self.bound = LatencyBound(
            stat=lb.stat,
            seconds=lb.seconds,
            window=lb.window,
            hysteresis_s=lb.hysteresis_s,
            better_margin=lb.better_margin,
        )
        self.params = params if params is not None else SchedulerParams()
        self.tick_s = tick_s
        self.ctl_timeout_s = ctl_timeout_s
        self.restore_grace_s = restore_grace_s
        self.profile_save_interval_s = profile_save_interval_s
        self.load_refresh_interval_s = load_refresh_interval_s
        # Set once the registry's token is declared: it serves from then on.
        self.ready = threading.Event()

        self._events: queue.Queue[_Event] = queue.Queue()
        self._lock = threading.Lock()  # guards everything below that callbacks touch
        self._windows = LatencyWindows(self.bound.window)
        self._sample_wall: dict[WindowKey, float] = {}  # wall clock of each window's newest sample
        self._dirty: set[WindowKey] = set()
        self._timeouts: dict[str, tuple[str, int]] = {}  # robot -> (deployment, consecutive)
        self._reroute_asked: set[str] = set()
        self._actions: dict[str, str] = {}
        self._last_telemetry: dict[str, float] = {}
        self._routes: dict[str, tuple[str | None, int]] = {}  # cache of the RIB's routes
        self._loads: dict[str, tuple[int, int | None]] = {}  # from probe reports, not yet saved
        self._robot_digests: dict[str, str] = {}
        self._followed: set[tuple[str, str]] = set()  # (role, id) reported by the subscriber
        self._bad_input_logged: dict[str, float] = {}
        # Control-loop state (only the control loop touches these).
        self._registrations: dict[str, _Registration] = {}
        self._cloud_tokens: set[str] = set()
        self._seen: set[str] = set()  # deployments accepted in this run
        self._confirmed: set[str] = set()  # robots whose route was confirmed in this run
        self._started_at = 0.0
        self._closing = False

        self.rib: Rib | None = None
        self.session: zenoh.Session | None = None
        self.transport: ZenohTransport | None = None
        self.switcher: Switcher | None = None
        self.scheduler: Scheduler | None = None
        self._fleet_digest: str | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._declared: list[Any] = []
        self._token: Any = None

    # -- lifecycle -----------------------------------------------------------------------------
    def startup(self) -> None:
        """Open the RIB and the session, declare everything, seed membership, then go live."""
        try:
            self._startup()
        except BaseException:
            self.shutdown()
            raise

    def _startup(self) -> None:
        self._started_at = time.monotonic()
        self.rib = rib = Rib(self.db_path)
        rib.reset_liveness()
        self._fleet_digest = fleet_model_digest(self.cfg)
        for route in rib.routes():
            self._routes[route.robot] = (route.deployment, route.epoch)
        self._restore_profiles(rib)
        if self.cfg.registry.embedded_router:
            self.session = session = open_session(self.cfg, router=True)
            where = ", ".join(self.cfg.registry.listen)
        else:
            self.session = session = open_session(self.cfg)
            where = f"the router at {self.cfg.registry.endpoint}"
        self.transport = ZenohTransport(session, self.fleet)
        self.switcher = Switcher(
            rib, self.transport, ctl_timeout_s=self.ctl_timeout_s, sender=self.id
        )
        self.scheduler = Scheduler(self.bound, self.params)
        self._pool = ThreadPoolExecutor(PROBE_WORKERS, thread_name_prefix="registry-probe")

        fleet = self.fleet
        declare = session.declare_queryable
        self._declared += [
            declare(keys.rib_all(fleet), self._guard(self._on_view)),
            declare(keys.reg_register(fleet), self._guard(self._on_register)),
            declare(keys.reg_reroute(fleet), self._guard(self._on_reroute)),
            declare(keys.reg_drain(fleet), self._guard(self._on_drain)),
            session.declare_subscriber(keys.tele_all(fleet), self._guard(self._on_telemetry)),
            session.declare_subscriber(
                keys.tele_probe_all(fleet), self._guard(self._on_probe_report)
            ),
        ]
        # Membership: follow changes from now on, then seed with what is alive already. Seeds are
        # dropped for ids the subscriber has reported since (its news are newer), so no order of
        # arrival leaves a dead token marked alive or a live one missed.
        liveliness = session.liveliness()
        self._declared.append(
            liveliness.declare_subscriber(keys.alive_all(fleet), self._guard(self._on_liveliness))
        )
        for reply in liveliness.get(keys.alive_all(fleet), timeout=PROBE_TIMEOUT_S):
            if reply.ok is not None:
                member = self._member(str(reply.ok.key_expr))
                if member is not None:
                    self._events.put(_Membership(member[0], member[1], True, seed=True))
        self._token = liveliness.declare_token(keys.alive_registry(fleet, self.id))
        self.ready.set()
        log.info(
            "registry %s of fleet %s: listening on %s, RIB %s (%d routes restored)",
            self.id,
            fleet,
            where,
            self.db_path,
            len(self._routes),
        )

    def main_loop(self) -> None:
        """The control loop: queued events at once, the scheduler every tick."""
        now = time.monotonic()
        next_tick = now
        next_save = now + self.profile_save_interval_s
        next_refresh = now + self.load_refresh_interval_s
        while not self.should_exit.is_set():
            wait_s = min(self.tick_s, max(0.0, next_tick - time.monotonic()))
            try:
                event: _Event | None = self._events.get(timeout=wait_s)
            except queue.Empty:
                event = None
            if event is not None:
                self._safely(self._handle, event)
            now = time.monotonic()
            if now >= next_tick:
                self._safely(self._schedule_all)
                next_tick = now + self.tick_s
            if now >= next_save:
                self._safely(self._save_profiles)
                next_save = now + self.profile_save_interval_s
            if now >= next_refresh:
                self._safely(self._refresh_deployments)
                next_refresh = now + self.load_refresh_interval_s

    def shutdown(self) -> None:
        """Token first, then every declaration, pending requests, the pool, the session, the
        RIB (profiles saved)."""
        self.ready.clear()
        self._closing = True
        if self._token is not None:
            _undeclare(self._token)
            self._token = None
        for entity in reversed(self._declared):
            _undeclare(entity)
        self._declared.clear()
        self._answer_pending()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self.rib is not None:
            self._safely(self._save_profiles)
            self._safely(self._flush_loads)
        if self.session is not None:
            self.session.close()
            self.session = None
        if self.rib is not None:
            self.rib.close()
            self.rib = None
        log.info("registry %s stopped", self.id)

    # -- callbacks (Zenoh threads: short, never a decision) --------------------------------------
    def _guard(self, fn: Callable[[Any], None]) -> Callable[[Any], None]:
        def callback(arg: Any) -> None:
            if self._closing:
                return
            try:
                fn(arg)
            except Exception:
                if not self._closing:
                    log.exception("registry: unexpected error in %s", fn.__name__)

        return callback

    def _member(self, key: str) -> tuple[str, str] | None:
        parts = keys.parse_key(key)
        if parts is None or parts.kind is not keys.KeyKind.ALIVE or parts.fleet != self.fleet:
            return None
        assert parts.role is not None and parts.id is not None
        if parts.role == "registry":
            if parts.id != self.id:
                log.warning("another registry (%s) is alive in fleet %s", parts.id, self.fleet)
            return None
        return parts.role, parts.id

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        member = self._member(str(sample.key_expr))
        if member is None:
            return
        with self._lock:
            self._followed.add(member)
        alive = sample.kind == zenoh.SampleKind.PUT
        self._events.put(_Membership(member[0], member[1], alive))

    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            rec = TelemetryRecord.from_wire(sample.payload.to_bytes(), max_bytes=MAX_REQUEST_BYTES)
            parts = keys.parse_key(key)
            if parts is None or parts.id != rec.robot:
                raise WireError(f"record of robot {rec.robot!r} published on {key}")
        except WireError as exc:
            self._bad_input(f"telemetry on {key}", str(exc))
            return
        now = time.monotonic()
        reroute = False
        with self._lock:
            robot = rec.robot
            self._actions[robot] = rec.action
            self._last_telemetry[robot] = time.time()
            if rec.cut is None:
                return  # computed on the robot: says nothing about any deployment
            route = self._routes.get(robot, (None, 0))[0]
            remote_s = rec.transfer_s + rec.cloud_s
            if not rec.fallback and rec.deployment is not None:
                self._add_sample(robot, rec.deployment, Source.TELEMETRY, remote_s, now, key)
                if rec.deployment == route:
                    self._timeouts.pop(robot, None)
                    self._reroute_asked.discard(robot)
            elif (
                rec.fallback
                and route is not None
                and (_is_timeout(rec.reason) or _is_unserved(rec.reason))
            ):
                if _is_timeout(rec.reason):
                    # A timeout took at least the deadline: the window sees it as that.
                    finite = remote_s if math.isfinite(remote_s) else 0.0
                    sample_s = max(self.cfg.deadline_s, finite)
                    self._add_sample(robot, route, Source.TELEMETRY, sample_s, now, key)
                on, count = self._timeouts.get(robot, (route, 0))
                count = count + 1 if on == route else 1
                self._timeouts[robot] = (route, count)
                if count >= self.params.timeout_count and robot not in self._reroute_asked:
                    self._reroute_asked.add(robot)
                    reroute = True
        if reroute:
            self._events.put(_Evaluate(rec.robot))

    def _on_probe_report(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            rep = ProbeReport.from_wire(sample.payload.to_bytes(), max_bytes=MAX_REQUEST_BYTES)
            parts = keys.parse_key(key)
            if parts is None or parts.id != rep.robot:
                raise WireError(f"report of robot {rep.robot!r} published on {key}")
        except WireError as exc:
            self._bad_input(f"probe report on {key}", str(exc))
            return
        if not rep.ok:
            return  # no measurement; a dead deployment shows in liveliness, a slow one in time
        value = rep.expected_latency_s if rep.expected_latency_s is not None else rep.rtt_s
        with self._lock:
            if value is not None:
                self._add_sample(
                    rep.robot, rep.deployment, Source.PROBE, value, time.monotonic(), key
                )
            if rep.load is not None:
                self._loads[rep.deployment] = (rep.load, rep.capacity)

    def _add_sample(
        self, robot: str, deployment: str, source: Source, value: float, at: float, key: str
    ) -> None:
        """Record one sample (caller holds the lock); a bad number is logged, not recorded."""
        try:
            self._windows.add(robot, deployment, source, value, at)
        except ValueError as exc:
            self._bad_input(f"{source.value} on {key}", str(exc))
            return
        wkey = (robot, deployment, source)
        self._sample_wall[wkey] = time.time()
        self._dirty.add(wkey)

    def _on_view(self, query: zenoh.Query) -> None:
        with query:
            views = [
                v
                for v in keys.RIB_VIEWS
                if zenoh.KeyExpr(keys.rib(self.fleet, v)).intersects(query.key_expr)
            ]
            if not views:
                reason = (
                    f"no RIB view at {query.key_expr}; views: {', '.join(keys.RIB_VIEWS)} "
                    f"under {keys.rib_all(self.fleet)}"
                )
                _reply(query, str(query.key_expr), _refusal(reason))
                return
            try:
                request = self._decode_query(query, msg.RibQuery, empty_ok=True)
            except WireError as exc:
                _reply(query, keys.rib(self.fleet, views[0]), error_reply(exc))
                return
            # A wildcard query (rib/*) gets every view it names, each on its own key.
            for view in views:
                _reply(query, keys.rib(self.fleet, view), self.view(view, request).to_wire())

    def _on_register(self, query: zenoh.Query) -> None:
        key = keys.reg_register(self.fleet)
        with query:
            try:
                request = self._decode_query(query, msg.RegisterRequest)
            except WireError as exc:
                _reply(query, key, error_reply(exc))
                return
            rib = self._rib()
            reason = msg.check_registration(
                request, service=self.service, model_digest=self._reference_digest(request.id)
            )
            route = None
            if reason is not None:
                self._refuse(request.role, request.id, reason)
            elif request.role == "robot":
                if request.model_digest:
                    with self._lock:
                        self._robot_digests[request.id] = request.model_digest
                row = rib.route(request.id)
                if row is not None:
                    route = self._route_change(request.id, row.deployment, row.epoch, "current")
            reply = msg.RegisterReply(
                accepted=reason is None,
                reason=reason or "accepted",
                protocol_version=msg.PROTOCOL_VERSION,
                route=route,
            )
            _reply(query, key, reply.to_wire())

    def _on_reroute(self, query: zenoh.Query) -> None:
        self._queue_request(query, msg.RerouteRequest, keys.reg_reroute(self.fleet))

    def _on_drain(self, query: zenoh.Query) -> None:
        self._queue_request(query, msg.DrainRequest, keys.reg_drain(self.fleet))

    def _queue_request(self, query: zenoh.Query, kind: type[Message], key: str) -> None:
        """Decode here (bad input is answered at once); the control loop acts and replies."""
        try:
            request = self._decode_query(query, kind)
        except WireError as exc:
            with query:
                _reply(query, key, error_reply(exc))
            return
        self._events.put(_Request(request, query, key))

    def _decode_query(
        self, query: zenoh.Query, kind: type[Message], *, empty_ok: bool = False
    ) -> Any:
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        if not data and empty_ok:
            return kind()
        return decode(data, expect=kind, max_bytes=MAX_REQUEST_BYTES)

    def _bad_input(self, where: str, problem: str) -> None:
        """Log a dropped publication; the same problem on the same key once per interval, so a
        misbehaving publisher cannot flood the log."""
        now = time.monotonic()
        seen = f"{where}: {problem}"
        with self._lock:
            last = self._bad_input_logged.get(seen)
            if last is not None and now - last < BAD_INPUT_LOG_INTERVAL_S:
                return
            if len(self._bad_input_logged) >= BAD_INPUT_LOG_KEYS:
                self._bad_input_logged.clear()
            self._bad_input_logged[seen] = now
        log.warning("ignored bad %s: %s", where, problem)

    # -- control loop ----------------------------------------------------------------------------
    def _safely(self, fn: Callable[..., None], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            log.exception("registry: unexpected error in %s", getattr(fn, "__name__", fn))

    def _handle(self, event: _Event) -> None:
        if isinstance(event, _Membership):
            self._on_membership(event)
        elif isinstance(event, _Probed):
            self._on_probed(event)
        elif isinstance(event, _Evaluate):
            self._evaluate(event.robot)
        elif isinstance(event.message, msg.DrainRequest):
            with event.query:
                _reply(event.query, event.key, self._drain(event.message).to_wire())
        elif isinstance(event.message, msg.RerouteRequest):
            with event.query:
                _reply(event.query, event.key, self._reroute(event.message).to_wire())

    def _on_membership(self, event: _Membership) -> None:
        if event.seed:
            with self._lock:
                if (event.role, event.id) in self._followed:
                    return  # the subscriber has newer news of this one
        rib = self._rib()
        if event.role == "robot":
            if event.alive:
                if event.id not in self.cfg.machines:
                    log.info("robot %s is not in the fleet file; serving it anyway", event.id)
                rib.upsert_robot(event.id, service=self.service)
                log.info("robot %s is up", event.id)
            elif rib.set_robot_alive(event.id, False, "liveliness token gone"):
                log.info("robot %s is gone", event.id)
                self._scheduler().forget(event.id)
                with self._lock:
                    self._windows.drop_robot(event.id)
                    self._timeouts.pop(event.id, None)
                    self._reroute_asked.discard(event.id)
            return
        deployment = event.id
        if event.alive:
            if deployment in self._cloud_tokens:
                return
            self._cloud_tokens.add(deployment)
            self._registrations[deployment] = _Registration("pending")
            self._submit_probe(deployment, refresh=False)
            return
        self._cloud_tokens.discard(deployment)
        registration = self._registrations.pop(deployment, None)
        with self._lock:
            self._windows.drop_deployment(deployment)  # a returning process starts clean
            self._loads.pop(deployment, None)
        if registration is None or registration.state != "accepted":
            return
        rib.set_deployment_alive(deployment, False, "liveliness token gone")
        log.info("deployment %s is gone", deployment)
        for route in rib.routes():
            if route.deployment == deployment:
                self._evaluate(route.robot)

    def _submit_probe(self, deployment: str, *, refresh: bool) -> None:
        if self._pool is None or self._closing:
            return
        self._pool.submit(self._probe_for_events, deployment, refresh)

    def _probe_for_events(self, deployment: str, refresh: bool) -> None:
        """Pool thread: probe a deployment and queue the outcome for the control loop."""
        attempts = 1 if refresh else REGISTRATION_ATTEMPTS
        reply, error = None, "no reply"
        transport = self.transport
        for _ in range(attempts):
            if self._closing or transport is None:
                return
            request = msg.ProbeRequest(sender=self.id, sent_at=time.time())
            try:
                reply = transport.probe(deployment, request, PROBE_TIMEOUT_S)
            except TransportError as exc:
                reply, error = None, str(exc)
            if reply is not None:
                break
            if error == "no reply":
                error = f"no probe reply within {PROBE_TIMEOUT_S:g} s ({attempts} tries)"
        self._events.put(_Probed(deployment, reply, error, refresh))

    def _on_probed(self, event: _Probed) -> None:
        deployment = event.deployment
        registration = self._registrations.get(deployment)
        if deployment not in self._cloud_tokens or registration is None:
            return  # gone meanwhile
        if event.refresh:
            if registration.state == "accepted" and event.reply is not None:
                self._apply_probe(deployment, event.reply)
            return
        reply = event.reply
        reason = event.error if reply is None else self._check_probe(deployment, reply)
        if reason is not None:
            if registration.reason != reason:
                self._refuse("cloud", deployment, reason)
            self._registrations[deployment] = _Registration("refused", reason, reply is None)
            return
        assert reply is not None
        rib = self._rib()
        rib.upsert_deployment(
            deployment,
            service=reply.service,
            model_digest=reply.model_digest,
            capacity=reply.capacity,
            version=f"protocol {reply.protocol_version}",
            load=reply.load,
        )
        self._registrations[deployment] = _Registration("accepted")
        self._seen.add(deployment)
        log.info(
            "deployment %s registered (service %s, model %s, capacity %d)",
            deployment,
            reply.service,
            reply.model_digest[:12],
            reply.capacity,
        )
        self._apply_probe(deployment, reply)
        self._restore_routes(deployment)

    def _check_probe(self, deployment: str, reply: msg.ProbeReply) -> str | None:
        if reply.deployment != deployment:
            return f"cloud {deployment!r} answers its probe as {reply.deployment!r}"
        request = msg.RegisterRequest(
            role="cloud",
            id=deployment,
            protocol_version=reply.protocol_version,
            capabilities=reply.capabilities,
            service=reply.service,
            model_digest=reply.model_digest or None,
        )
        return msg.check_registration(
            request, service=self.service, model_digest=self._reference_digest(deployment)
        )

    def _reference_digest(self, asking: str) -> str | None:
        """The model digest everyone must match: the fleet file's model when this host has it,
        else the one of the deployments accepted already."""
        if self._fleet_digest is not None:
            return self._fleet_digest
        for row in self._rib().deployments():
            if row.alive and row.id != asking and row.model_digest and row.service == self.service:
                return row.model_digest
        return None

    def _refuse(self, role: str, machine: str, reason: str) -> None:
        self._rib().record_event(
            EventKind.REGISTRATION_REFUSED,
            robot=machine if role == "robot" else None,
            deployment=machine if role == "cloud" else None,
            reason=reason,
        )
        log.warning("refused %s %s: %s", role, machine, reason)

    def _apply_probe(self, deployment: str, reply: msg.ProbeReply) -> None:
        """Load from a probe, and anycast repair: a deployment serving a robot the RIB routes
        elsewhere is put back in standby."""
        row = self._rib().deployment(deployment)
        if row is not None and (row.load, row.capacity) != (reply.load, reply.capacity):
            self._rib().update_deployment_load(deployment, reply.load, reply.capacity)
        for robot, state in reply.states.items():
            if state is not msg.DeploymentState.SERVICE:
                continue
            route = self._routes.get(robot, (None, 0))
            if route[0] != deployment and (route[0] is not None or route[1] > 0):
                log.warning(
                    "deployment %s serves %s, routed to %s: putting it in standby",
                    deployment,
                    robot,
                    route[0] or "local",
                )
                self._switcher().fence(robot, deployment, at_least=reply.epochs.get(robot, 0))

    def _restore_routes(self, deployment: str) -> None:
        """Re-assert every restored route to this deployment that this run has not confirmed."""
        for route in self._rib().routes():
            if route.deployment != deployment or route.robot in self._confirmed:
                continue
            result = self._switcher().reassert(route.robot)
            if result.attempts and result.attempts[-1].outcome is Outcome.ACKED:
                self._confirmed.add(route.robot)
                self._route_set(result)
                if not result.changed:
                    # Tell the robot again (receivers ignore an epoch they hold already).
                    self._publish(route.robot, deployment, result.epoch, "restore")
                log.info(
                    "restored route %s -> %s (epoch %d)", route.robot, deployment, result.epoch
                )
            else:
                detail = result.attempts[-1].detail if result.attempts else result.reason
                log.warning(
                    "cannot restore route %s -> %s: %s; rerouting",
                    route.robot,
                    deployment,
                    detail,
                )
                self._evaluate(route.robot, unusable=frozenset({deployment}))

    def _refresh_deployments(self) -> None:
        self._flush_loads()
        for deployment, registration in list(self._registrations.items()):
            if registration.state == "accepted":
                self._submit_probe(deployment, refresh=True)
            elif registration.retry:
                self._submit_probe(deployment, refresh=False)

    def _flush_loads(self) -> None:
        with self._lock:
            loads, self._loads = self._loads, {}
        rib = self._rib()
        for deployment, (load, capacity) in loads.items():
            row = rib.deployment(deployment)
            if row is not None and row.alive and (row.load, row.capacity) != (load, capacity):
                rib.update_deployment_load(deployment, load, capacity)

    # -- decisions -------------------------------------------------------------------------------
    def _schedule_all(self) -> None:
        for robot in self._rib().robots():
            if robot.alive:
                self._evaluate(robot.id)

    def _waiting_for(self, robot: str, route: str | None) -> str | None:
        """The deployment a decision about `robot` should wait for (registration in flight, or a
        restored route's deployment not reconnected yet), else None."""
        target = route
        if target is None and robot in self.cfg.machines:
            target = self.cfg.initial_service(robot)
        if target is None:
            return None
        registration = self._registrations.get(target)
        if registration is not None and registration.state == "pending":
            return target
        in_grace = time.monotonic() - self._started_at < self.restore_grace_s
        if target not in self._seen and in_grace:
            return target
        return None

    def _evaluate(
        self, robot: str, *, unusable: frozenset[str] = frozenset()
    ) -> SwitchResult | None:
        """Ask the scheduler about one robot and carry out its decision (control loop only)."""
        rib = self._rib()
        route_row = rib.route(robot)
        current = route_row.deployment if route_row else None
        if not unusable and self._waiting_for(robot, current) is not None:
            return None
        deployments = [
            DeploymentView(
                id=row.id,
                service=row.service,
                alive=row.alive and row.id not in unusable,
                draining=row.draining,
                load=row.load,
                capacity=row.capacity,
                model_digest=row.model_digest or None,
            )
            for row in rib.deployments()
        ]
        robot_row = rib.robot(robot)
        with self._lock:
            telemetry = self._windows.stats(robot, current, Source.TELEMETRY) if current else None
            timeouts_on, timeouts = self._timeouts.get(robot, (None, 0))
            profiles = self._windows.profiles(robot, Source.PROBE)
            digest = self._robot_digests.get(robot)
        view = RobotView(
            id=robot,
            service=robot_row.service if robot_row is not None else self.service,
            route=current,
            telemetry=telemetry,
            timeouts=timeouts,
            timeouts_on=timeouts_on,
            model_digest=digest,
        )
        decision = self._scheduler().evaluate(view, deployments, profiles)
        if decision is None:
            return None
        return self._carry_out(self._prefer_initial(decision))

    def _prefer_initial(self, decision: Decision) -> Decision:
        """An initial placement goes to initial_policy's service machine when it can."""
        if decision.reason is not Reason.INITIAL or decision.robot not in self.cfg.machines:
            return decision
        wanted = self.cfg.initial_service(decision.robot)
        if wanted is None or wanted not in decision.candidates:
            return decision
        order = (wanted, *(c for c in decision.candidates if c != wanted))
        return Decision(
            decision.robot, decision.from_deployment, wanted, decision.reason, order, None
        )

    def _carry_out(self, decision: Decision) -> SwitchResult:
        switcher, scheduler = self._switcher(), self._scheduler()
        if decision.reason is Reason.INITIAL:
            # A placement is not a move: it must not start the scheduler's dwell time, or a
            # robot placed on a slow deployment would wait min_dwell_s on top of the hysteresis.
            result = switcher.apply(decision)
            if not result.changed and result.attempts:
                scheduler.record_failure(decision.robot)
        else:
            result = carry_out(scheduler, switcher, decision)
        if result.changed:
            self._confirmed.add(decision.robot)
            self._route_set(result)
            log.info(
                "route %s: %s -> %s (epoch %d, %s)",
                result.robot,
                result.previous or "local",
                result.deployment or "local",
                result.epoch,
                decision.reason.value,
            )
        elif result.attempts:
            tried = ", ".join(f"{a.deployment}: {a.outcome.value}" for a in result.attempts)
            log.warning("route %s not moved (%s): %s", result.robot, decision.reason.value, tried)
        return result

    def _route_set(self, result: SwitchResult) -> None:
        """Bookkeeping after the RIB's route of a robot changed or was confirmed."""
        with self._lock:
            before = self._routes.get(result.robot)
            self._routes[result.robot] = (result.deployment, result.epoch)
            if before is None or before[0] != result.deployment:
                # Samples from an earlier stay on the new deployment must not count now.
                if result.deployment is not None:
                    self._windows.window(result.robot, result.deployment, Source.TELEMETRY).clear()
                self._timeouts.pop(result.robot, None)
                self._reroute_asked.discard(result.robot)

    def _drain(self, request: msg.DrainRequest) -> Message:
        """Move every robot of a deployment that stops; the reply lists the robots moved."""
        deployment = request.deployment
        rib = self._rib()
        if rib.deployment(deployment) is None and deployment not in self._registrations:
            return ErrorReply.make(
                ErrorCode.REFUSED, f"unknown deployment {deployment!r}: it never registered here"
            )
        rib.set_deployment_draining(deployment, request.reason or "drain requested")
        log.info("deployment %s drains: moving its robots", deployment)
        moved: list[str] = []
        stuck: list[str] = []
        for route in rib.routes():
            if route.deployment != deployment:
                continue
            result = self._evaluate(route.robot)
            if result is not None and result.changed:
                moved.append(route.robot)
            else:
                stuck.append(route.robot)
        reason = ""
        if stuck:
            reason = (
                f"no other deployment took {', '.join(stuck)}; they compute locally once it stops"
            )
            log.warning("drain of %s: %s", deployment, reason)
        return msg.DrainReply(ok=not stuck, moved=tuple(moved), reason=reason)

    def _reroute(self, request: msg.RerouteRequest) -> Message:
        """A robot's request for another deployment: answered with its route afterwards."""
        robot = request.robot
        rib = self._rib()
        if rib.robot(robot) is None:
            return ErrorReply.make(
                ErrorCode.REFUSED, f"unknown robot {robot!r}: its liveliness token was never seen"
            )
        route = rib.route(robot)
        if route is None or route.deployment is None:
            self._evaluate(robot)
        elif not 0 < request.epoch < route.epoch:
            # The route failing the robot is the current one (or the robot does not know which it
            # holds): a forced move, as after timeouts. An older epoch: it has moved already.
            with self._lock:
                self._timeouts[robot] = (
                    route.deployment,
                    max(request.consecutive_timeouts, self.params.timeout_count),
                )
            self._evaluate(robot)
        now = rib.route(robot)
        moved = now is not None and (route is None or now.epoch != route.epoch)
        return self._route_change(
            robot,
            now.deployment if now else None,
            now.epoch if now else 0,
            "rerouted" if moved else "current route",
        )

    def _publish(self, robot: str, deployment: str | None, epoch: int, reason: str) -> None:
        try:
            self._transport().publish_route(self._route_change(robot, deployment, epoch, reason))
        except TransportError as exc:
            log.warning("%s", exc)

    def _route_change(
        self, robot: str, deployment: str | None, epoch: int, reason: str
    ) -> msg.RouteChange:
        return msg.RouteChange(
            robot=robot, deployment=deployment, epoch=epoch, reason=reason, at=time.time()
        )

    def _answer_pending(self) -> None:
        """Requests still queued at shutdown get a refusal instead of a timeout."""
        while True:
            try:
                event = self._events.get_nowait()
            except queue.Empty:
                return
            if isinstance(event, _Request):
                with event.query:
                    _reply(event.query, event.key, _refusal(STOPPING_REASON))

    # -- profiles --------------------------------------------------------------------------------
    def _restore_profiles(self, rib: Rib) -> None:
        now_m, now_w = time.monotonic(), time.time()
        for row in rib.profiles():
            try:
                source = Source(row.source)
            except ValueError:
                continue
            # Keep each window's age: the scheduler ignores probe windows older than its limit.
            at = now_m - max(0.0, now_w - row.updated_at)
            window = self._windows.window(row.robot, row.deployment, source)
            try:
                window.extend(row.samples, at)
            except ValueError:
                window.clear()
                continue
            self._sample_wall[(row.robot, row.deployment, source)] = row.updated_at

    def _save_profiles(self) -> None:
        with self._lock:
            dirty, self._dirty = self._dirty, set()
            rows = []
            for wkey in dirty:
                robot, deployment, source = wkey
                samples = self._windows.window(robot, deployment, source).samples()
                if samples:
                    rows.append((robot, deployment, source, samples, self._sample_wall[wkey]))
        rib = self._rib()
        for robot, deployment, source, samples, updated_at in rows:
            rib.save_profile(robot, deployment, source.value, samples, updated_at)

    # -- views -----------------------------------------------------------------------------------
    def view(self, name: str, query: msg.RibQuery | None = None) -> Message:
        """The reply of the RIB view `name` (one of keys.RIB_VIEWS) under `query`'s filters."""
        q = query if query is not None else msg.RibQuery()
        now = time.time()
        if name == "deployments":
            return msg.DeploymentsView(rows=tuple(self._deployment_rows(q)), generated_at=now)
        if name == "robots":
            return msg.RobotsView(rows=tuple(self._robot_rows(q)), generated_at=now)
        if name == "routes":
            return msg.RoutesView(rows=tuple(self._route_rows(q)), generated_at=now)
        if name == "events":
            return msg.EventsView(rows=tuple(self._event_rows(q)), generated_at=now)
        if name == "profiles":
            return msg.ProfilesView(rows=tuple(self._profile_rows(q)), generated_at=now)
        raise UserError(f"unknown RIB view {name!r}; known: {', '.join(keys.RIB_VIEWS)}")

    def _deployment_rows(self, q: msg.RibQuery) -> Iterable[msg.DeploymentRow]:
        rib = self._rib()
        refused = {
            d: r.reason for d, r in list(self._registrations.items()) if r.state == "refused"
        }
        listed: set[str] = set()
        for row in rib.deployments():
            if q.deployment is not None and row.id != q.deployment:
                continue
            listed.add(row.id)
            states = rib.deployment_states(deployment=row.id)
            extra: dict[str, Any] = {
                "version": row.version,
                "draining": row.draining,
                "epochs": {s.robot: s.epoch for s in states},
            }
            if row.id in refused:
                extra["refused"] = refused[row.id]
            yield msg.DeploymentRow(
                id=row.id,
                service=row.service,
                alive=row.alive,
                model_digest=row.model_digest or None,
                states={s.robot: s.state for s in states},
                load=row.load,
                capacity=row.capacity,
                last_seen=row.last_seen,
                extra=extra,
            )
        for deployment, reason in sorted(refused.items()):
            if deployment not in listed and q.deployment in (None, deployment):
                yield msg.DeploymentRow(
                    id=deployment, service="", alive=False, extra={"refused": reason}
                )

    def _robot_rows(self, q: msg.RibQuery) -> Iterable[msg.RobotRow]:
        rib = self._rib()
        for row in rib.robots():
            if q.robot is not None and row.id != q.robot:
                continue
            route = rib.route(row.id)
            deployment = route.deployment if route else None
            state = "local" if route is not None and deployment is None else "unrouted"
            if deployment is not None:
                states = rib.deployment_states(robot=row.id, deployment=deployment)
                state = states[0].state.value if states else "service"
            with self._lock:
                stats = (
                    self._windows.stats(row.id, deployment, Source.TELEMETRY)
                    if deployment
                    else None
                )
                action = self._actions.get(row.id)
                timeouts = self._timeouts.get(row.id, (None, 0))[1]
                last_telemetry = self._last_telemetry.get(row.id)
            yield msg.RobotRow(
                id=row.id,
                service=row.service,
                alive=row.alive,
                deployment=deployment,
                epoch=route.epoch if route else 0,
                bound_stat=Stat(self.bound.stat).value,
                bound_s=self.bound.seconds,
                window_stat_s=stats.value(self.bound.stat) if stats else None,
                window_len=stats.count if stats else 0,
                deadline_s=self.cfg.deadline_s,
                action=action,
                extra={
                    "state": state,
                    "consecutive_timeouts": timeouts,
                    "last_seen": row.last_seen,
                    "last_telemetry": last_telemetry,
                },
            )

    def _route_rows(self, q: msg.RibQuery) -> Iterable[msg.RouteRow]:
        rib = self._rib()
        for route in rib.routes():
            if q.robot is not None and route.robot != q.robot:
                continue
            if q.deployment is not None and route.deployment != q.deployment:
                continue
            last = rib.events(limit=1, robot=route.robot, kind=EventKind.ROUTE.value)
            yield msg.RouteRow(
                robot=route.robot,
                deployment=route.deployment,
                epoch=route.epoch,
                since=route.since,
                reason=last[0].reason if last else "",
            )

    def _event_rows(self, q: msg.RibQuery) -> Iterable[msg.EventRow]:
        limit = min(q.limit or DEFAULT_EVENTS_LIMIT, MAX_EVENTS_LIMIT)
        if limit < 1:
            return
        fetch = MAX_EVENTS_LIMIT if q.deployment is not None else limit
        rows = self._rib().events(fetch, robot=q.robot)
        if q.deployment is not None:
            rows = [e for e in rows if e.deployment == q.deployment][-limit:]
        for e in rows:
            yield msg.EventRow(
                seq=e.seq,
                at=e.ts,
                kind=e.kind,
                reason=e.reason,
                robot=e.robot,
                deployment=e.deployment,
                epoch=e.epoch,
            )

    def _profile_rows(self, q: msg.RibQuery) -> Iterable[msg.ProfileRow]:
        with self._lock:
            items = [
                (key, window.stats(), self._sample_wall.get(key))
                for key, window in self._windows.items()
                if key[2] is Source.PROBE
            ]
        for (robot, deployment, _), stats, updated_at in sorted(items, key=lambda i: i[0][:2]):
            if (
                stats is None
                or q.robot not in (None, robot)
                or q.deployment not in (None, deployment)
            ):
                continue
            yield msg.ProfileRow(
                robot=robot,
                deployment=deployment,
                samples=stats.count,
                median_s=stats.median,
                mean_s=stats.mean,
                p95_s=stats.p95,
                max_s=stats.max,
                stddev_s=stats.stddev,
                updated_at=updated_at,
            )

    # -- accessors (set in startup) --------------------------------------------------------------
    def _rib(self) -> Rib:
        if self.rib is None:
            raise RuntimeError("the registry is not started")
        return self.rib

    def _switcher(self) -> Switcher:
        if self.switcher is None:
            raise RuntimeError("the registry is not started")
        return self.switcher

    def _scheduler(self) -> Scheduler:
        if self.scheduler is None:
            raise RuntimeError("the registry is not started")
        return self.scheduler

    def _transport(self) -> ZenohTransport:
        if self.transport is None:
            raise RuntimeError("the registry is not started")
        return self.transport


def _refusal(reason: str) -> bytes:
    return ErrorReply.make(ErrorCode.REFUSED, reason).to_wire()


def _reply(query: zenoh.Query, key: str, payload: bytes) -> None:
    """Reply, tolerating a querier that went away (its timeout passed, its session closed)."""
    try:
        query.reply(key, payload)
    except zenoh.ZError as exc:
        log.debug("cannot reply on %s: %s", key, zenoh_error_text(exc))


def _undeclare(entity: Any) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError as exc:
        log.debug("undeclare failed: %s", zenoh_error_text(exc))


def run_registry(cfg: FleetConfig, *, db_path: str | Path | None = None) -> int:
    """Run the registry in this (main) thread until SIGINT/SIGTERM; returns the exit code."""
    return RegistryDaemon(cfg, db_path=db_path).run()
