"""registry.registration without a network: a deployment's registration from its probe reply
(accepted, refused with a reason, retried when it did not answer), robot registration, and the
reference model digest. The RIB lives in memory."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import pytest

from common import keys
from common.wire import WireError
from common.wire.registry import (
    CAP_CTL,
    CAP_INFER,
    CAP_LOCAL_FALLBACK,
    CAP_PROBE,
    NO_CAPACITY_REASON,
    PROTOCOL_VERSION,
    ProbeReply,
    RegisterRequest,
)
from registry.registration import Registrar, RegistrationState, Role
from registry.rib import MEMORY, EventKind, Rib

SERVICE = "vision"
DIGEST = "a" * 64
OTHER_DIGEST = "b" * 64


@pytest.fixture
def rib() -> Iterator[Rib]:
    with Rib(MEMORY) as rib:
        yield rib


def reply(deployment: str, digest: str = DIGEST, **changes: object) -> ProbeReply:
    fields: dict[str, object] = {
        "deployment": deployment,
        "protocol_version": PROTOCOL_VERSION,
        "capabilities": (CAP_INFER, CAP_PROBE, CAP_CTL),
        "service": SERVICE,
        "model_digest": digest,
        "states": {},
        "load": 1,
        "capacity": 4,
    }
    fields.update(changes)
    return ProbeReply(**fields)  # type: ignore[arg-type]


def refusals(rib: Rib) -> list[str]:
    return [e.reason for e in rib.events(kind=EventKind.REGISTRATION_REFUSED.value)]


def test_the_vocabularies_are_the_wire_values() -> None:
    assert [r.value for r in Role] == list(keys.ROLES)
    assert [s.value for s in RegistrationState] == ["pending", "accepted", "refused"]


def test_a_deployment_is_pending_until_its_probe_reply_accepts_it(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    assert registrar.token_came("edge-1")
    assert not registrar.token_came("edge-1"), "a token reported twice is one registration"
    assert registrar.is_state("edge-1", RegistrationState.PENDING)
    assert not registrar.seen("edge-1")
    assert registrar.admit("edge-1", reply("edge-1"), "")
    assert registrar.is_state("edge-1", RegistrationState.ACCEPTED) and registrar.seen("edge-1")
    row = rib.deployment("edge-1")
    assert row is not None and (row.alive, row.load, row.capacity) == (True, 1, 4)
    assert registrar.to_probe() == [("edge-1", True)], "accepted: refreshed now and then"


def test_a_wrong_model_is_refused_once_with_the_reason(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("edge-1")
    assert not registrar.admit("edge-1", reply("edge-1", OTHER_DIGEST), "")
    assert not registrar.admit("edge-1", reply("edge-1", OTHER_DIGEST), "")
    registration = registrar.get("edge-1")
    assert registration is not None and registration.state is RegistrationState.REFUSED
    assert "same model" in registration.reason and not registration.retry
    assert registrar.refused() == {"edge-1": registration.reason}
    assert len(refusals(rib)) == 1, "the same refusal is recorded once"
    assert rib.deployment("edge-1") is None, "never in the RIB, never routed to"
    assert registrar.to_probe() == []


def test_a_deployment_that_did_not_answer_is_probed_again(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("edge-1")
    assert not registrar.admit("edge-1", None, "no probe reply within 0.5 s (3 tries)")
    assert registrar.to_probe() == [("edge-1", False)], "a registration again, not a refresh"
    assert registrar.admit("edge-1", reply("edge-1"), "")
    assert registrar.refused() == {}


def test_a_probe_answered_under_another_name_is_refused(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("edge-1")
    assert not registrar.admit("edge-1", reply("edge-9"), "")
    assert "'edge-9'" in registrar.refused()["edge-1"]


def test_a_deployment_gone_meanwhile_is_left_alone(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("edge-1")
    gone = registrar.token_gone("edge-1")
    assert gone is not None and gone.state is RegistrationState.PENDING
    assert not registrar.admit("edge-1", reply("edge-1"), "")
    assert rib.deployment("edge-1") is None
    assert not registrar.refresh("edge-1", reply("edge-1"))


def test_a_refresh_writes_the_load_of_an_accepted_deployment(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("edge-1")
    registrar.admit("edge-1", reply("edge-1"), "")
    assert registrar.refresh("edge-1", reply("edge-1", load=3, capacity=8))
    row = rib.deployment("edge-1")
    assert row is not None and (row.load, row.capacity) == (3, 8)


def test_without_the_model_file_the_first_deployment_accepted_sets_the_reference(
    rib: Rib,
) -> None:
    registrar = Registrar("f", rib, SERVICE, None)
    registrar.token_came("edge-1")
    registrar.token_came("edge-2")
    assert registrar.admit("edge-1", reply("edge-1", OTHER_DIGEST), "")
    assert registrar.reference_digest("edge-2") == OTHER_DIGEST
    assert registrar.reference_digest("edge-1") is None, "nobody else to match"
    assert not registrar.admit("edge-2", reply("edge-2", DIGEST), "")


def test_robot_registration_keeps_its_digest_and_refusals_name_the_robot(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    request = RegisterRequest(
        role="robot",
        id="robot-1",
        protocol_version=PROTOCOL_VERSION,
        capabilities=(CAP_LOCAL_FALLBACK,),
        service=SERVICE,
        model_digest=DIGEST,
    )
    assert registrar.register(request) is None
    assert registrar.robot_digest("robot-1") == DIGEST
    wrong = RegisterRequest(
        role="robot",
        id="robot-2",
        protocol_version=PROTOCOL_VERSION + 1,
        capabilities=(CAP_LOCAL_FALLBACK,),
        service=SERVICE,
    )
    reason = registrar.register(wrong)
    assert reason is not None and "protocol" in reason
    [event] = rib.events(kind=EventKind.REGISTRATION_REFUSED.value)
    assert (event.robot, event.deployment) == ("robot-2", None)
    assert registrar.robot_digest("robot-2") is None


def test_a_robot_announces_its_frames_in_flight_at_registration(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    request = robot_request("robot-1")
    assert registrar.register(request) is None
    assert registrar.robot_in_flight("robot-1") is None, "an older robot announces nothing"
    piped = RegisterRequest.from_wire(dataclasses.replace(request, max_in_flight=3).to_wire())
    assert piped.max_in_flight == 3
    assert registrar.register(piped) is None
    assert registrar.robot_in_flight("robot-1") == 3
    with pytest.raises(WireError, match="max_in_flight: must be at least 1"):
        dataclasses.replace(request, max_in_flight=0)


def robot_request(robot: str) -> RegisterRequest:
    return RegisterRequest(
        role="robot",
        id=robot,
        protocol_version=PROTOCOL_VERSION,
        capabilities=(CAP_LOCAL_FALLBACK,),
        service=SERVICE,
        model_digest=DIGEST,
    )


def test_a_robot_left_local_for_capacity_is_told_why_when_it_registers(rib: Rib) -> None:
    # Regression: the reply said `current`, so a robot that registered again after the
    # registry refused it for capacity did not know why it computes locally.
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    rib.set_route("robot-1", None, rib.reserve_epoch("robot-1"), NO_CAPACITY_REASON)
    reply = registrar.reply_to(robot_request("robot-1"))
    assert reply.accepted and reply.route is not None
    assert (reply.route.deployment, reply.route.reason) == (None, NO_CAPACITY_REASON)


def test_a_robot_with_a_deployment_gets_its_current_route(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    rib.set_route("robot-1", None, rib.reserve_epoch("robot-1"), NO_CAPACITY_REASON)
    rib.set_route("robot-1", "edge-1", rib.reserve_epoch("robot-1"), "initial")
    reply = registrar.reply_to(robot_request("robot-1"))
    assert reply.route is not None
    assert (reply.route.deployment, reply.route.reason) == ("edge-1", "current")
    assert registrar.reply_to(robot_request("robot-2")).route is None, "never routed"


def _deployment(rib: Rib, name: str, *, load: int, capacity: int = 4, **changes: str) -> None:
    fields = {"service": SERVICE, "model_digest": DIGEST, **changes}
    rib.upsert_deployment(
        name,
        service=fields["service"],
        model_digest=fields["model_digest"],
        capacity=capacity,
        version="1",
        load=load,
    )


def test_a_robot_refused_for_capacity_learns_it_in_its_registration_reply(rib: Rib) -> None:
    # Regression (issue 26): a new robot learned it was refused for capacity one round later,
    # from the route change; the reply said nothing.
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    _deployment(rib, "edge-1", load=4)
    _deployment(rib, "edge-2", load=6, capacity=6)
    reply = registrar.reply_to(robot_request("robot-1"))
    assert reply.accepted and reply.route is not None
    assert (reply.route.deployment, reply.route.reason) == (None, NO_CAPACITY_REASON)
    assert reply.route.epoch == 0, "not an epoch of its own: the round's route supersedes it"


def test_a_robot_is_not_refused_while_one_deployment_that_can_serve_it_has_room(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    _deployment(rib, "edge-1", load=4)
    _deployment(rib, "edge-2", load=3)
    assert registrar.reply_to(robot_request("robot-1")).route is None, "placed by the round"
    rib.set_deployment_alive("edge-2", False)
    _deployment(rib, "edge-3", load=0, model_digest=OTHER_DIGEST)  # another model: not a target
    refused = registrar.reply_to(robot_request("robot-2")).route
    assert refused is not None and refused.reason == NO_CAPACITY_REASON


def test_with_no_deployment_at_all_the_robot_is_not_told_capacity(rib: Rib) -> None:
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    assert registrar.reply_to(robot_request("robot-1")).route is None


def test_a_deployment_on_fewer_providers_than_asked_is_accepted_with_a_warning(
    rib: Rib, caplog: pytest.LogCaptureFixture
) -> None:
    # Its machine allows it (`providers_fallback: allow`); the registry says so, once.
    registrar = Registrar("f", rib, SERVICE, DIGEST)
    registrar.token_came("gpu-1")
    fell_back = reply("gpu-1", providers=("CPUExecutionProvider",), providers_fallback=True)
    with caplog.at_level("INFO", logger="registry.registration"):
        assert registrar.admit("gpu-1", fell_back, "")
    assert "capacity 4, on CPUExecutionProvider)" in caplog.text
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warnings == [
        "deployment gpu-1 serves on CPUExecutionProvider, without an accelerator its machine "
        "asks for"
    ]
