"""A cloud daemon serving several services, over real Zenoh on loopback (its `run()` in a thread).

The fleet has a zoo model service (`vision`), a Python handler service (`tags`, a module written
next to the fleet file, which is searched first) and a handler service the deployment does not
serve (`extra`). One deployment serves `vision` and `tags`, each in a plane of its own: a ctl
`service` naming one service declares only that service's key; each key answers with its own
service's results (a handler's equal to calling the function directly); a handler that raises
or returns something that is not arrays gets a named error reply and the next request is served;
a probe or ctl naming a service not served here gets a named `unknown_service` refusal while the
daemon keeps serving; SIGTERM's drain takes every service's robots to the registry at once.
"""

from __future__ import annotations

import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh

from cloudd.daemon import CloudDaemon
from cloudd.refusals import RefusalReason
from common import keys
from common.config import FleetConfig, load_fleet
from common.fleet_model import fleet_split_model
from common.handlers import HANDLER_INPUT
from common.partition import sample_feeds
from common.partition.runtime import SplitModel
from common.wire import ErrorCode, ErrorReply
from common.wire.cloud_to_robot import InferReply
from common.wire.registry import (
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    DrainReply,
    FaultSpec,
    ProbeReply,
    ProbeRequest,
)
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor
from tests.integration.conftest import Router, running_cloud
from tests.integration.test_cloudd import RESULT_ATOL, STOP_WITHIN_S, ask, ask_one, wait_reply

DEPLOYMENT = "edge-1"
ROBOT = "robot-1"
MODEL_SERVICE = "vision"
HANDLER_SERVICE = "tags"
NOT_SERVED = "extra"
START_WAIT_S = 60.0
"""The first start builds and splits the zoo model."""
ABSENT_WAIT_S = 1.0
"""How long a key that must not answer is given (its declaration would have come with the
other service's, on the same session)."""
TAG_IMAGE = (3, 16, 16)
MODEL_IMAGE = (3, 32, 32)
SCALE = 2.0

HANDLER_SOURCE = '''"""A test handler: the image's mean (times `scale`) and shape; fails on
purpose on a frame whose brightest pixel is 255 (raises) or 254 (returns a list)."""

import numpy as np


def detect(inputs, scale=1.0):
    image = inputs["image"]
    brightest = int(image.max())
    if brightest == 255:
        raise ValueError("saturated frame")
    if brightest == 254:
        return [1, 2, 3]
    return {
        "mean": np.array([image.mean() * scale], dtype=np.float32),
        "shape": np.array(image.shape, dtype=np.int64),
    }


def other(inputs):
    return {"one": np.ones(1, dtype=np.float32)}
'''


@dataclass
class Fleet:
    """The running deployment, the config, the handler function and the model run here."""

    daemon: CloudDaemon
    cfg: FleetConfig
    detect: Callable[..., dict[str, np.ndarray]]
    model: SplitModel


@pytest.fixture
def fleet(tmp_path: Path, zenoh_router: Router) -> Iterator[Fleet]:
    module = f"ef_test_tags_{uuid.uuid4().hex[:8]}"  # a name of its own: modules are cached
    (tmp_path / f"{module}.py").write_text(HANDLER_SOURCE, encoding="utf-8")
    data: dict[str, Any] = {
        "fleet": f"s-{uuid.uuid4().hex[:8]}",
        "services": {
            MODEL_SERVICE: {"model": "zoo:vgg", "input_shape": list(MODEL_IMAGE)},
            HANDLER_SERVICE: {
                "handler": f"{module}:detect",
                "params": {"scale": SCALE},
                "input_shape": list(TAG_IMAGE),
            },
            NOT_SERVED: {"handler": f"{module}:other", "input_shape": list(TAG_IMAGE)},
        },
        "registry": {"endpoint": zenoh_router.endpoint, "listen": [zenoh_router.endpoint]},
        "machines": {
            DEPLOYMENT: {
                "role": "cloud",
                "listen": ["tcp/127.0.0.1:0"],
                "services": [MODEL_SERVICE, HANDLER_SERVICE],
            },
            ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
        },
        "initial_policy": {DEPLOYMENT: "service"},
        "latency_bound": {"seconds": 0.5},
        "deadline_s": 1.0,
    }
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")  # file order matters
    cfg = load_fleet(path)
    model = fleet_split_model(cfg.for_service(MODEL_SERVICE), lazy=True)
    with running_cloud(cfg, DEPLOYMENT, START_WAIT_S) as daemon:
        yield Fleet(daemon, cfg, sys.modules[module].detect, model)


# -- helpers ---------------------------------------------------------------------------------------
def connect(open_peer: Callable[..., zenoh.Session], fleet: Fleet, wait: Any) -> zenoh.Session:
    """A peer session that sees the deployment (its token and its probe key)."""
    session = open_peer()
    wait(session, keys.alive_deployment(fleet.cfg.fleet, DEPLOYMENT))
    assert isinstance(wait_reply(session, keys.dep_probe(fleet.cfg.fleet, DEPLOYMENT)), ProbeReply)
    return session


def ctl(
    session: zenoh.Session, fleet: Fleet, op: CtlOp, epoch: int, service: str | None
) -> CtlReply | ErrorReply:
    request = CtlRequest(op=op, robot=ROBOT, epoch=epoch, sender="test", service=service)
    reply = ask_one(session, keys.dep_ctl(fleet.cfg.fleet, DEPLOYMENT), request.to_wire())
    assert isinstance(reply, (CtlReply, ErrorReply)), reply
    return reply


def probe(session: zenoh.Session, fleet: Fleet, service: str | None) -> ProbeReply | ErrorReply:
    request = ProbeRequest(sender="test", sent_at=time.time(), service=service)
    reply = ask_one(session, keys.dep_probe(fleet.cfg.fleet, DEPLOYMENT), request.to_wire())
    assert isinstance(reply, (ProbeReply, ErrorReply)), reply
    return reply


def svc_key(fleet: Fleet, service: str) -> str:
    return keys.svc_infer(fleet.cfg.fleet, service, ROBOT)


def request(digest: str, tensors: dict[str, np.ndarray], frame: int, cut: int = 0) -> bytes:
    return InferRequest(
        robot=ROBOT,
        frame=frame,
        model_digest=digest,
        cut=cut,
        tensors={n: EncodedTensor.raw(a) for n, a in tensors.items()},
        deadline_s=5.0,
        sent_at=time.time(),
    ).to_wire()


def tag_image(seed: int, brightest: int = 200) -> np.ndarray:
    """A handler's image (1xHxWx3 uint8) whose brightest pixel is `brightest`."""
    _, h, w = TAG_IMAGE
    image = np.random.default_rng(seed).integers(0, 100, size=(1, h, w, 3), dtype=np.uint8)
    image[0, 0, 0, 0] = brightest
    return image


def serve(session: zenoh.Session, fleet: Fleet, service: str, epoch: int) -> CtlReply:
    reply = ctl(session, fleet, CtlOp.SERVICE, epoch, service)
    assert isinstance(reply, CtlReply), reply
    assert reply.ok and reply.state is DeploymentState.SERVICE, reply
    assert reply.service == service and reply.deployment == DEPLOYMENT
    return reply


def handler_digest(session: zenoh.Session, fleet: Fleet) -> str:
    profile = probe(session, fleet, HANDLER_SERVICE)
    assert isinstance(profile, ProbeReply), profile
    return profile.model_digest


# -- tests -----------------------------------------------------------------------------------------
def test_each_service_has_its_own_state_key_and_answers(
    fleet: Fleet, open_peer, wait_for_token
) -> None:
    session = connect(open_peer, fleet, wait_for_token)
    # The probe names its service; none is the fleet's first.
    vision, tags = probe(session, fleet, MODEL_SERVICE), probe(session, fleet, HANDLER_SERVICE)
    assert isinstance(vision, ProbeReply) and isinstance(tags, ProbeReply)
    assert (vision.service, vision.model_digest) == (MODEL_SERVICE, fleet.model.digest)
    assert vision.num_cuts == fleet.model.num_cuts > 1
    assert (tags.service, tags.num_cuts) == (HANDLER_SERVICE, 1)
    assert tags.model_digest not in ("", vision.model_digest)
    first = probe(session, fleet, None)
    assert isinstance(first, ProbeReply) and first.service == MODEL_SERVICE
    assert vision.states == tags.states == {ROBOT: DeploymentState.STANDBY}

    # Service for the handler only: its key answers, the model's does not.
    serve(session, fleet, HANDLER_SERVICE, epoch=1)
    image = tag_image(seed=1)
    answer = wait_reply(
        session,
        svc_key(fleet, HANDLER_SERVICE),
        request(tags.model_digest, {HANDLER_INPUT: image}, 1),
    )
    assert isinstance(answer, InferReply), answer
    assert (answer.frame, answer.deployment, answer.epoch) == (1, DEPLOYMENT, 1)
    expected = fleet.detect({HANDLER_INPUT: image}, scale=SCALE)
    assert set(answer.outputs) == set(expected)
    for name, value in expected.items():
        np.testing.assert_array_equal(answer.outputs[name], value, err_msg=name)
    model_request = request(fleet.model.digest, sample_feeds(fleet.model.input_specs(), 3), 2)
    assert ask(session, svc_key(fleet, MODEL_SERVICE), model_request, ABSENT_WAIT_S) == []
    vision, tags = probe(session, fleet, MODEL_SERVICE), probe(session, fleet, HANDLER_SERVICE)
    assert isinstance(vision, ProbeReply) and isinstance(tags, ProbeReply)
    assert vision.states == {ROBOT: DeploymentState.STANDBY}
    assert tags.states == {ROBOT: DeploymentState.SERVICE} and tags.served == {ROBOT: 1}

    # Then the model too, at its own epoch: every cut equals the full model run here.
    serve(session, fleet, MODEL_SERVICE, epoch=7)
    feeds = sample_feeds(fleet.model.input_specs(), seed=11)
    full = fleet.model.run_full(feeds)
    key = svc_key(fleet, MODEL_SERVICE)
    wait_reply(session, key, model_request)
    for cut in range(fleet.model.num_cuts):
        tensors = fleet.model.run_prefix(cut, feeds)
        reply = ask_one(session, key, request(fleet.model.digest, tensors, 10 + cut, cut))
        assert isinstance(reply, InferReply), f"cut {cut}: {reply!r}"
        assert reply.epoch == 7 and set(reply.outputs) == set(full)
        for name, value in full.items():
            err = float(np.max(np.abs(reply.outputs[name] - value)))
            assert err <= RESULT_ATOL, f"cut {cut} output {name}: max abs error {err}"

    # Standby in one service leaves the other serving.
    standby = ctl(session, fleet, CtlOp.STANDBY, 2, HANDLER_SERVICE)
    assert isinstance(standby, CtlReply) and standby.ok and standby.service == HANDLER_SERVICE
    again = request(tags.model_digest, {HANDLER_INPUT: image}, 3)
    assert ask(session, svc_key(fleet, HANDLER_SERVICE), again, ABSENT_WAIT_S) == []
    assert isinstance(ask_one(session, key, model_request), InferReply)
    assert fleet.daemon.states(MODEL_SERVICE)[ROBOT].state is DeploymentState.SERVICE
    assert fleet.daemon.states(HANDLER_SERVICE)[ROBOT].state is DeploymentState.STANDBY


def test_a_failing_handler_gets_a_named_error_and_the_next_frame_is_served(
    fleet: Fleet, open_peer, wait_for_token
) -> None:
    session = connect(open_peer, fleet, wait_for_token)
    digest = handler_digest(session, fleet)
    serve(session, fleet, HANDLER_SERVICE, epoch=1)
    key = svc_key(fleet, HANDLER_SERVICE)
    good = tag_image(seed=5)
    assert isinstance(
        wait_reply(session, key, request(digest, {HANDLER_INPUT: good}, 0)), InferReply
    )
    for frame, (brightest, needle) in enumerate(
        [(255, "raised ValueError: saturated frame"), (254, "returned list")], start=1
    ):
        bad = ask_one(
            session, key, request(digest, {HANDLER_INPUT: tag_image(frame, brightest)}, frame)
        )
        assert isinstance(bad, ErrorReply), bad
        assert bad.error_code is ErrorCode.INTERNAL, bad
        assert needle in bad.reason and "detect" in bad.reason, bad.reason
        after = ask_one(session, key, request(digest, {HANDLER_INPUT: good}, 10 + frame))
        assert isinstance(after, InferReply), f"after frame {frame}: {after!r}"
        expected = fleet.detect({HANDLER_INPUT: good}, scale=SCALE)
        np.testing.assert_array_equal(after.outputs["mean"], expected["mean"])


def test_a_service_not_served_here_gets_a_named_refusal(
    fleet: Fleet, open_peer, wait_for_token
) -> None:
    session = connect(open_peer, fleet, wait_for_token)
    cases = [
        ("nope", "unknown service 'nope'"),
        (NOT_SERVED, f"{DEPLOYMENT} does not serve '{NOT_SERVED}'"),
    ]
    for service, needle in cases:
        for what, reply in (
            ("ctl", ctl(session, fleet, CtlOp.SERVICE, 1, service)),
            ("probe", probe(session, fleet, service)),
        ):
            assert isinstance(reply, ErrorReply), f"{what} {service}: {reply!r}"
            assert reply.error_code is ErrorCode.UNKNOWN_SERVICE, reply
            assert needle in reply.reason, reply.reason
            assert f"{MODEL_SERVICE}, {HANDLER_SERVICE}" in reply.reason, reply.reason
    assert fleet.daemon.refusals.get(RefusalReason.UNKNOWN_SERVICE) == 4
    # Nothing declared for the refused service, and the daemon keeps serving the others.
    assert ask(session, svc_key(fleet, NOT_SERVED), b"", ABSENT_WAIT_S) == []
    serve(session, fleet, MODEL_SERVICE, epoch=2)
    fault = CtlRequest(op=CtlOp.FAULT, fault=FaultSpec(), sender="test", service=HANDLER_SERVICE)
    reply = ask_one(session, keys.dep_ctl(fleet.cfg.fleet, DEPLOYMENT), fault.to_wire())
    assert isinstance(reply, CtlReply) and reply.ok and reply.service == HANDLER_SERVICE


def test_drain_asks_once_and_every_service_is_moved_within_2s(
    fleet: Fleet, open_peer, wait_for_token
) -> None:
    daemon = fleet.daemon
    registry = connect(open_peer, fleet, wait_for_token)
    asked: list[bytes] = []

    def move_robots(query: zenoh.Query) -> None:
        # As the registry does: each service's robot to standby at a newer epoch, then answer.
        asked.append(query.payload.to_bytes() if query.payload is not None else b"")
        done = [ctl(registry, fleet, CtlOp.STANDBY, 5, s) for s in daemon.services]
        ok = all(isinstance(r, CtlReply) and r.ok for r in done)
        query.reply(keys.reg_drain(fleet.cfg.fleet), DrainReply(ok=ok, moved=(ROBOT,)).to_wire())
        query.drop()

    def on_drain(query: zenoh.Query) -> None:
        threading.Thread(target=move_robots, args=(query,), daemon=True).start()

    queryable = registry.declare_queryable(keys.reg_drain(fleet.cfg.fleet), on_drain)
    try:
        serve(registry, fleet, MODEL_SERVICE, epoch=1)
        serve(registry, fleet, HANDLER_SERVICE, epoch=1)
        thread = next(t for t in threading.enumerate() if t.name == f"cloud-{DEPLOYMENT}")
        t0 = time.monotonic()
        daemon.stop(drain=True)
        thread.join(STOP_WITHIN_S * 2)
        took = time.monotonic() - t0
    finally:
        queryable.undeclare()
    assert not thread.is_alive() and took <= STOP_WITHIN_S, f"stopped after {took:.2f} s"
    assert len(asked) == 1 and daemon.drained.is_set()
    for service in (MODEL_SERVICE, HANDLER_SERVICE):
        assert daemon.states(service)[ROBOT].state is DeploymentState.STANDBY, service
