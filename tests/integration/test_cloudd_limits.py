"""The cloud daemon's limits over real Zenoh on loopback (its `run()` in a thread).

One deployment with limits below the fleet's (`machines.edge-1.limits`): a request, probe or ctl
payload over its request limit, a tensor declaring more than its tensor limit (a compressed
bomb), a probe asking for more echo than its cap and a request whose body names another robot
than its key each get a named error reply; the next good request is served; every refusal is
counted by reason, read the same from the daemon, from its probe reply and from its exit log.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from cloudd.daemon import CloudDaemon
from cloudd.refusals import RefusalReason
from common.partition.runtime import SplitModel
from common.wire import ErrorCode, ErrorReply
from common.wire.cloud_to_robot import InferReply
from common.wire.registry import CtlOp, ProbeReply, ProbeRequest
from common.wire.tensor_codecs import encode_tensor_as
from tests.integration.conftest import Router
from tests.integration.test_cloudd import (
    MAX_PAYLOAD_BYTES,
    POLL_S,
    ROBOT,
    WAIT_S,
    ask_one,
    connect,
    ctl,
    ctl_key,
    fleet_config,
    infer_request,
    probe,
    probe_key,
    reference,
    serve,
    svc_key,
    tiny_path,
)

# The fixtures shared with the daemon's main integration tests (pytest finds them by name).
__all__ = ["reference", "tiny_path"]

REQUEST_LIMIT = 100 * 1024
"""Above a good request of the tiny model (64 KiB of tensor), below the fleet's limit."""
TENSOR_LIMIT = 1 << 20
"""Above the tiny model's cut tensors (64 KiB each)."""
ECHO_CAP = 1000
OVER_REQUEST_LIMIT = bytes(REQUEST_LIMIT + 1)

assert REQUEST_LIMIT < MAX_PAYLOAD_BYTES, "the deployment's limit, not the fleet's, is tested"


@dataclasses.dataclass
class Running:
    """A ready daemon and its thread; `stop()` returns once `run()` has returned."""

    daemon: CloudDaemon
    thread: threading.Thread

    def stop(self) -> None:
        self.daemon.stop()
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "the daemon did not stop"


@pytest.fixture
def limited(zenoh_router: Router, tiny_path: Path) -> Iterator[Running]:
    limits = {
        "max_request_bytes": REQUEST_LIMIT,
        "max_tensor_bytes": TENSOR_LIMIT,
        "max_echo_bytes": ECHO_CAP,
    }
    fleet = f"l-{uuid.uuid4().hex[:8]}"
    cfg = fleet_config(tiny_path, zenoh_router.endpoint, fleet, limits=limits)
    daemon = CloudDaemon(cfg, "edge-1")
    running = Running(daemon, threading.Thread(target=daemon.run, name="cloud-edge-1", daemon=True))
    running.thread.start()
    deadline = time.monotonic() + WAIT_S * 3  # the first start splits the model
    while not running.daemon.ready.wait(POLL_S):
        assert running.thread.is_alive() and time.monotonic() < deadline, "edge-1 did not start"
    try:
        yield running
    finally:
        running.stop()


def test_limits_refuse_with_named_errors_and_count_each_reason(
    limited: Running,
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    reference: SplitModel,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    daemon = limited.daemon
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference)
    good = infer_request(reference, 1, frame=7)
    bomb = dataclasses.replace(
        good,
        tensors={
            # Compressed to a few KiB, declaring 4 MiB: without the limit the model check
            # would refuse it too, but only after reading its shape against the cut's.
            name: encode_tensor_as(np.zeros((TENSOR_LIMIT // 1024, 1024), np.float32), "raw+zstd")
            for name in good.tensors
        },
    )
    cases: list[tuple[str, str, bytes, ErrorCode, list[str]]] = [
        ("request over the limit", svc_key(daemon), OVER_REQUEST_LIMIT, ErrorCode.TOO_LARGE,
         [f"limit of {REQUEST_LIMIT} bytes"]),
        ("probe over the limit", probe_key(daemon), OVER_REQUEST_LIMIT, ErrorCode.TOO_LARGE,
         [f"limit of {REQUEST_LIMIT} bytes"]),
        ("ctl over the limit", ctl_key(daemon), OVER_REQUEST_LIMIT, ErrorCode.TOO_LARGE,
         [f"limit of {REQUEST_LIMIT} bytes"]),
        ("tensor bomb", svc_key(daemon), bomb.to_wire(), ErrorCode.TOO_LARGE,
         ["limits.max_tensor_bytes", str(TENSOR_LIMIT * 4)]),
        ("another robot's body", svc_key(daemon),
         dataclasses.replace(good, robot="robot-2").to_wire(), ErrorCode.WRONG_ROBOT,
         ["'robot-2'", f"'{ROBOT}'"]),
        ("echo over the cap", probe_key(daemon),
         ProbeRequest(sender="test", sent_at=0.0, echo_bytes=ECHO_CAP + 1).to_wire(),
         ErrorCode.TOO_LARGE, ["limits.max_echo_bytes", str(ECHO_CAP + 1)]),
    ]  # fmt: skip
    for what, key, payload, code, needles in cases:
        reply = ask_one(session, key, payload)
        assert isinstance(reply, ErrorReply), f"{what}: {reply!r}"
        assert reply.code == code.value, f"{what}: {reply.code} ({reply.reason})"
        for needle in needles:
            assert needle in reply.reason, f"{what}: {needle!r} not in {reply.reason!r}"
        after = ask_one(session, svc_key(daemon), good.to_wire())
        assert isinstance(after, InferReply), f"after {what}: {after!r}"

    # Under the caps, the same keys serve.
    assert len(probe(session, daemon, echo_bytes=ECHO_CAP).echo) == ECHO_CAP
    assert ctl(session, daemon, CtlOp.SERVICE, 1).ok

    expected = {
        RefusalReason.REQUEST_TOO_LARGE.value: 3,
        RefusalReason.TENSOR_TOO_LARGE.value: 1,
        RefusalReason.WRONG_ROBOT.value: 1,
        RefusalReason.ECHO_TOO_LARGE.value: 1,
    }
    assert daemon.refusals.snapshot() == expected
    profile = ask_one(session, probe_key(daemon))
    assert isinstance(profile, ProbeReply) and profile.refused == expected

    limited.stop()
    summary = [m for m in caplog.messages if "refused (reason, count)" in m]
    assert len(summary) == 1, caplog.messages
    for reason, count in expected.items():
        assert f"{reason} {count}" in summary[0], summary[0]
