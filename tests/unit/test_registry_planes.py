"""registry.planes and registry.plane without a network: one plane per service, and the dispatch
of what reaches the daemon to the planes it concerns (registration, reroute, membership, probe
outcomes, publications, views), with a service the fleet lacks refused by name. The RIBs live in
memory; the transport and the probers are stand-ins that record what they are asked."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.keys import Role
from common.membership import MemberChange
from common.metrics import new_registry
from common.models import file_digest
from common.throttled_log import ThrottledLog
from common.wire import ErrorCode
from common.wire.registry import (
    CAP_CTL,
    CAP_INFER,
    CAP_LOCAL_FALLBACK,
    CAP_PROBE,
    PROTOCOL_VERSION,
    ProbeReply,
    RegisterRequest,
    RerouteRequest,
    RibQuery,
)
from common.wire.telemetry import FallbackReason, ProbeReport
from registry.metrics import RegistryMetrics
from registry.plane import Plane, build_plane, plane_db_path, plane_measurements
from registry.planes import Planes
from registry.prober import Probed
from registry.publications import PublicationReader
from registry.refusals import Refusals
from registry.registration import RegistrationState
from registry.replies import UnknownService
from registry.requests import QueuedRequest, RequestQueue
from registry.rib import MEMORY, EventKind, Rib
from registry.scheduler import Reason, SchedulerParams

DETECT, SEGMENT = "detect", "segment"


def services_fleet(tmp_path: Path) -> FleetConfig:
    """edge-1 serves both services, edge-2 `detect` only; robot-1 uses both, robot-2 `segment`."""
    models = {}
    for name in (DETECT, SEGMENT):
        models[name] = tmp_path / f"{name}.onnx"
        models[name].write_bytes(name.encode())
    return fleet_from_dict(
        {
            "fleet": "f",
            "services": {name: {"model": str(path)} for name, path in models.items()},
            "machines": {
                "edge-1": {"role": "cloud"},
                "edge-2": {"role": "cloud", "services": [DETECT]},
                "robot-1": {"role": "robot"},
                "robot-2": {"role": "robot", "services": [SEGMENT]},
            },
            "initial_policy": {"robot-1": "robot", "robot-2": "robot", "edge-1": "service"},
            "latency_bound": {"stat": "median", "seconds": 0.1},
            "deadline_s": 0.5,
        }
    )


class Prober:
    """The probes a plane submits."""

    def __init__(self) -> None:
        self.submitted: list[tuple[str, bool]] = []

    def submit(self, deployment: str, *, refresh: bool) -> None:
        self.submitted.append((deployment, refresh))


class Dispatch:
    """Each service's plane over an in-memory RIB, and their `Planes`."""

    def __init__(self, cfg: FleetConfig) -> None:
        self.cfg = cfg
        self.ribs = {name: Rib(MEMORY) for name in cfg.services}
        self.probers = {name: Prober() for name in cfg.services}
        params = SchedulerParams()
        planes: list[Plane] = []
        for name in cfg.services:
            view = cfg.for_service(name)
            planes.append(
                build_plane(
                    view,
                    self.ribs[name],
                    plane_measurements(view, params, lambda where, problem: None),
                    transport=cast(Any, None),  # nothing here switches
                    prober=cast(Any, self.probers[name]),
                    sender="registry",
                    params=params,
                    ctl_timeout_s=0.5,
                    throttled=ThrottledLog(logging.getLogger("registry.daemon")),
                    started_at=0.0,
                    restore_grace_s=0.0,
                    metrics=RegistryMetrics(None),
                    max_request_bytes=64 * 1024,
                )
            )
        self.planes = Planes(cfg, planes, max_request_bytes=64 * 1024)

    def close(self) -> None:
        for rib in self.ribs.values():
            rib.close()


@pytest.fixture
def dispatch(tmp_path: Path) -> Iterator[Dispatch]:
    d = Dispatch(services_fleet(tmp_path))
    try:
        yield d
    finally:
        d.close()


def robot_request(robot: str, service: str, cfg: FleetConfig) -> RegisterRequest:
    path = cfg.for_service(service).model_path if service in cfg.services else None
    return RegisterRequest(
        role=Role.ROBOT,
        id=robot,
        protocol_version=PROTOCOL_VERSION,
        capabilities=(CAP_LOCAL_FALLBACK,),
        service=service,
        model_digest=file_digest(path) if path is not None else None,
    )


def refusals(rib: Rib) -> list[str]:
    return [e.reason for e in rib.events(kind=EventKind.REGISTRATION_REFUSED.value)]


def test_one_plane_per_service_each_with_its_own_rib_file() -> None:
    assert plane_db_path(Path("/var/ef/fleet.rib.sqlite"), DETECT, first=True) == Path(
        "/var/ef/fleet.rib.sqlite"
    ), "the first service keeps the configured file (a one-service fleet's is unchanged)"
    assert plane_db_path(Path("/var/ef/fleet.rib.sqlite"), SEGMENT, first=False) == Path(
        "/var/ef/fleet.rib.segment.sqlite"
    )
    assert plane_db_path(MEMORY, SEGMENT, first=False) == MEMORY


def test_planes_follow_the_fleet_file(dispatch: Dispatch) -> None:
    planes = dispatch.planes
    assert planes.services == [DETECT, SEGMENT] and len(planes) == 2
    assert planes.get(None) is planes.first and planes.first.service == DETECT
    assert [p.service for p in planes.holding("edge-1")] == [DETECT, SEGMENT]
    assert [p.service for p in planes.holding("edge-2")] == [DETECT]
    assert [p.service for p in planes.holding("robot-2")] == [SEGMENT]
    # A machine the fleet file does not name: a peer of a one-service fleet, the first service.
    assert [p.service for p in planes.holding("edge-9")] == [DETECT]
    with pytest.raises(UnknownService, match="'track'; this fleet's services: detect, segment"):
        planes.get("track")


def test_a_registration_goes_to_its_services_plane_and_an_unknown_service_is_refused(
    dispatch: Dispatch,
) -> None:
    planes, cfg = dispatch.planes, dispatch.cfg
    refused = planes.reply_to_register(robot_request("robot-1", "track", cfg))
    assert not refused.accepted
    assert refused.reason == "robot 'robot-1' serves 'track', this fleet serves 'detect', 'segment'"
    assert refusals(dispatch.ribs[DETECT]) == [refused.reason], "recorded by the first service"
    # A service the fleet file does not give that machine is refused in that service's plane.
    other = planes.reply_to_register(robot_request("robot-2", DETECT, cfg))
    assert not other.accepted and "its services: segment" in other.reason
    assert refusals(dispatch.ribs[DETECT])[-1] == other.reason
    # Once per service: each plane keeps the robot's own digest for its service.
    for service in (DETECT, SEGMENT):
        reply = planes.reply_to_register(robot_request("robot-1", service, cfg))
        assert reply.accepted, reply.reason
    detect, segment = planes.get(DETECT), planes.get(SEGMENT)
    assert detect.registrar.robot_digest("robot-1") != segment.registrar.robot_digest("robot-1")
    assert not refusals(dispatch.ribs[SEGMENT])


def test_a_reroute_for_a_service_the_fleet_lacks_is_refused_before_it_is_queued() -> None:
    queued: list[QueuedRequest] = []
    requests = RequestQueue("f", queued.append, max_request_bytes=1024, services=[DETECT, SEGMENT])

    def query(service: str | None) -> Any:
        request = RerouteRequest(
            robot="robot-1",
            deployment="edge-1",
            epoch=1,
            reason=FallbackReason.TIMEOUT,
            service=service,
        )
        payload = request.to_wire()
        return type("Query", (), {"payload": type("P", (), {"to_bytes": lambda _: payload})()})()

    with pytest.raises(UnknownService) as refused:
        requests.on_reroute(query("track"))
    assert refused.value.code is ErrorCode.UNKNOWN_SERVICE
    assert "'track'" in str(refused.value) and "detect, segment" in str(refused.value)
    requests.on_reroute(query(SEGMENT))
    requests.on_reroute(query(None))  # a robot of a one-service fleet: the first service
    assert [q.message.service for q in queued] == [SEGMENT, None]  # type: ignore[attr-defined]


def test_events_go_to_the_planes_they_concern(dispatch: Dispatch) -> None:
    planes = dispatch.planes

    def member(role: Role, machine: str, alive: bool = True) -> MemberChange:
        return MemberChange(role.value, machine, alive, False, frozenset({machine}))

    planes.handle(member(Role.CLOUD, "edge-2"))
    planes.handle(member(Role.CLOUD, "edge-1"))
    planes.handle(member(Role.ROBOT, "robot-2"))
    assert dispatch.probers[DETECT].submitted == [("edge-2", False), ("edge-1", False)]
    assert dispatch.probers[SEGMENT].submitted == [("edge-1", False)]
    assert [r.id for r in dispatch.ribs[SEGMENT].robots()] == ["robot-2"]
    assert dispatch.ribs[DETECT].robots() == [], "robot-2 does not use detect"

    # A probe outcome goes to the plane that asked for it.
    cfg = dispatch.cfg
    reply = ProbeReply(
        deployment="edge-1",
        protocol_version=PROTOCOL_VERSION,
        capabilities=(CAP_INFER, CAP_PROBE, CAP_CTL),
        service=SEGMENT,
        model_digest=file_digest(cast(Path, cfg.for_service(SEGMENT).model_path)),
        states={},
        load=0,
        capacity=4,
    )
    planes.handle(Probed("edge-1", reply, "", refresh=False, service=SEGMENT))
    segment, detect = planes.get(SEGMENT), planes.get(DETECT)
    assert segment.registrar.is_state("edge-1", RegistrationState.ACCEPTED)
    assert detect.registrar.is_state("edge-1", RegistrationState.PENDING)
    assert [(d.id, d.service) for d in dispatch.ribs[SEGMENT].deployments()] == [
        ("edge-1", SEGMENT)
    ]
    assert dispatch.ribs[DETECT].deployments() == []


def test_the_views_are_every_planes_rows_each_naming_its_service(dispatch: Dispatch) -> None:
    planes = dispatch.planes
    dispatch.ribs[DETECT].upsert_robot("robot-1", service=DETECT)
    dispatch.ribs[SEGMENT].upsert_robot("robot-1", service=SEGMENT)
    for service in (DETECT, SEGMENT):
        rib = dispatch.ribs[service]
        rib.set_route("robot-1", None, rib.reserve_epoch("robot-1"), "no_capacity")
    routes = planes.views.view("routes").rows  # type: ignore[attr-defined]
    assert [(r.robot, r.service) for r in routes] == [("robot-1", DETECT), ("robot-1", SEGMENT)]
    robots = planes.views.view("robots").rows  # type: ignore[attr-defined]
    assert [(r.id, r.service) for r in robots] == [("robot-1", DETECT), ("robot-1", SEGMENT)]
    events = planes.views.view("events").rows  # type: ignore[attr-defined]
    assert {e.service for e in events} == {DETECT, SEGMENT}
    assert [e.at for e in events] == sorted(e.at for e in events), "merged by time"
    assert len(planes.views.view("events", RibQuery(limit=1)).rows) == 1  # type: ignore[attr-defined]
    only = planes.views.view("routes", RibQuery(service=SEGMENT)).rows  # type: ignore[attr-defined]
    assert [r.service for r in only] == [SEGMENT]


def test_a_publication_of_a_service_the_fleet_lacks_is_counted_and_dropped() -> None:
    refusals, bad = Refusals(), []
    reader = PublicationReader(
        refusals,
        lambda where, problem: bad.append((where, problem)),
        max_bytes=4096,
        services=[DETECT, SEGMENT],
    )
    report = ProbeReport(
        robot="robot-1", deployment="edge-1", ok=True, at=1.0, rtt_s=0.01, service="track"
    )
    key = keys.tele_probe("f", "robot-1")
    sample = type(
        "Sample",
        (),
        {
            "key_expr": key,
            "payload": type("P", (), {"to_bytes": lambda _: report.to_wire()})(),
        },
    )()
    assert reader.read(sample, ProbeReport, "probe report") is None
    assert refusals.snapshot() == {"probe report": {ErrorCode.UNKNOWN_SERVICE.value: 1}}
    assert bad and "'track'" in bad[0][1]


def test_registry_metrics_count_per_service_beside_the_fleet_totals(dispatch: Dispatch) -> None:
    registry = new_registry()
    metrics = RegistryMetrics(registry, lambda: dispatch.ribs, services=[DETECT, SEGMENT])
    changes = "elasticfog_registry_service_route_changes_total"
    assert registry.get_sample_value(changes, {"service": SEGMENT, "reason": "initial"}) == 0
    metrics.route_change(Reason.DEPLOYMENT_LOST.value, "edge-1", service=SEGMENT)
    metrics.route_change(Reason.INITIAL.value, None, service=DETECT)
    assert (
        registry.get_sample_value(changes, {"service": SEGMENT, "reason": "deployment_lost"}) == 1
    )
    assert registry.get_sample_value(changes, {"service": DETECT, "reason": "initial"}) == 1
    failovers = "elasticfog_registry_service_failovers_total"
    assert registry.get_sample_value(failovers, {"service": SEGMENT}) == 1
    assert registry.get_sample_value(failovers, {"service": DETECT}) == 0
    # The fleet's totals keep their labels.
    assert registry.get_sample_value("elasticfog_registry_failovers_total", {}) == 1
    # Read from each service's RIB, a series per service.
    dispatch.ribs[SEGMENT].upsert_robot("robot-2", service=SEGMENT)
    alive = "elasticfog_registry_robots_alive"
    assert registry.get_sample_value(alive, {"service": SEGMENT}) == 1
    assert registry.get_sample_value(alive, {"service": DETECT}) == 0
