"""A cloud daemon's limits (cloudd.limits) and its refusal counts (cloudd.refusals), no network:
the limits resolved from the fleet file, each check at, under and over its limit, the reason each
refusal is counted as, and the summary logged at exit."""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import pytest

from cloudd.limits import CloudLimits
from cloudd.refusals import RefusalReason, Refusals, check_refusal, decode_refusal
from common.config import DEFAULT_MAX_ECHO_BYTES, DEFAULT_MAX_TENSOR_BYTES, fleet_from_dict
from common.errors import UserError
from common.partition import TensorSpec
from common.wire import (
    ErrorCode,
    ErrorReply,
    MalformedPayload,
    PayloadTooLarge,
    TensorTooLarge,
)
from common.wire.registry import ProbeRequest
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor, encode_tensor_as

FLEET_PAYLOAD_BYTES = 1 << 20
TENSOR_LIMIT = 4096


def fleet(**edge: Any) -> dict[str, Any]:
    return {
        "service": "vision",
        "model": "zoo:vgg",
        "deadline_s": 0.5,
        "latency_bound": {"seconds": 0.3},
        "max_payload_bytes": FLEET_PAYLOAD_BYTES,
        "machines": {"edge-1": {"role": "cloud", **edge}, "robot-1": {"role": "robot"}},
        "initial_policy": {"edge-1": "service"},
    }


def limits_of(**edge: Any) -> CloudLimits:
    cfg = fleet_from_dict(fleet(**edge))
    return CloudLimits.of(cfg, cfg.machine("edge-1"))


def infer(**tensors: EncodedTensor) -> InferRequest:
    return InferRequest(
        robot="robot-1",
        frame=1,
        model_digest="ab" * 32,
        cut=0,
        tensors=tensors,
        deadline_s=0.5,
        sent_at=time.time(),
    )


# -- limits from the fleet file --------------------------------------------------------------------
def test_defaults_take_the_fleet_payload_limit_and_sane_caps() -> None:
    limits = limits_of()
    assert limits == CloudLimits(
        request_bytes=FLEET_PAYLOAD_BYTES,
        tensor_bytes=DEFAULT_MAX_TENSOR_BYTES,
        echo_bytes=DEFAULT_MAX_ECHO_BYTES,
    )
    # Robots ask for 4 KiB of echo (robotd.frame_path.probes): the default cap must let them.
    assert DEFAULT_MAX_ECHO_BYTES >= 4096


def test_a_machines_limits_override_the_fleets() -> None:
    limits = limits_of(
        limits={"max_request_bytes": 2048, "max_tensor_bytes": 100, "max_echo_bytes": 10}
    )
    assert limits == CloudLimits(request_bytes=2048, tensor_bytes=100, echo_bytes=10)
    assert "2048" in limits.describe() and "probe echo up to 10" in limits.describe()


@pytest.mark.parametrize(
    ("section", "needle"),
    [
        ({"max_request_bytes": 0}, "limits.max_request_bytes: Input should be greater than"),
        ({"max_tensor_bytes": -1}, "limits.max_tensor_bytes: Input should be greater than"),
        ({"max_echo_bytes": 0}, "limits.max_echo_bytes: Input should be greater than"),
        ({"max_echo_byte": 10}, "did you mean 'max_echo_bytes'?"),
    ],
    ids=["zero request", "negative tensor", "zero echo", "typo"],
)
def test_a_bad_limit_names_its_field(section: dict[str, int], needle: str) -> None:
    with pytest.raises(UserError, match=needle):
        fleet_from_dict(fleet(limits=section))


# -- the checks ------------------------------------------------------------------------------------
def test_tensor_limit_counts_declared_bytes_not_wire_bytes() -> None:
    limits = CloudLimits(request_bytes=FLEET_PAYLOAD_BYTES, tensor_bytes=TENSOR_LIMIT, echo_bytes=1)
    at_limit = np.zeros(TENSOR_LIMIT // 4, np.float32)
    assert limits.tensor_refusal(infer(x=EncodedTensor.raw(at_limit))) is None
    # A few dozen compressed bytes that declare 64 times the limit: refused unopened.
    bomb = encode_tensor_as(np.zeros((16, TENSOR_LIMIT), np.float32), "raw+zstd")
    assert bomb.nbytes < TENSOR_LIMIT
    reply = limits.tensor_refusal(infer(x=EncodedTensor.raw(at_limit), y=bomb))
    assert reply is not None and reply.error_code is ErrorCode.TOO_LARGE
    assert "'y'" in reply.reason and str(16 * TENSOR_LIMIT * 4) in reply.reason
    assert "limits.max_tensor_bytes" in reply.reason and str(TENSOR_LIMIT) in reply.reason


def test_echo_cap() -> None:
    limits = CloudLimits(request_bytes=FLEET_PAYLOAD_BYTES, tensor_bytes=1, echo_bytes=1000)
    assert limits.echo_refusal(ProbeRequest(sender="robot-1", sent_at=0.0, echo_bytes=1000)) is None
    reply = limits.echo_refusal(ProbeRequest(sender="robot-1", sent_at=0.0, echo_bytes=1001))
    assert reply is not None and reply.error_code is ErrorCode.TOO_LARGE
    assert "1001" in reply.reason and "limits.max_echo_bytes" in reply.reason


def test_cut_tensors_over_the_limit_are_named() -> None:
    limits = CloudLimits(request_bytes=FLEET_PAYLOAD_BYTES, tensor_bytes=TENSOR_LIMIT, echo_bytes=1)
    specs = [
        [TensorSpec("x", "float32", (1, TENSOR_LIMIT // 4))],
        [TensorSpec("a", "float32", (1, TENSOR_LIMIT)), TensorSpec("b", "uint8", (8,))],
    ]
    assert limits.oversized_tensors(specs) == [f"cut 1 'a' ({TENSOR_LIMIT * 4} bytes)"]


# -- refusal reasons and counts --------------------------------------------------------------------
def test_each_refusal_is_counted_under_its_own_reason() -> None:
    assert decode_refusal(PayloadTooLarge("big")) is RefusalReason.REQUEST_TOO_LARGE
    assert decode_refusal(TensorTooLarge("big")) is RefusalReason.TENSOR_TOO_LARGE
    assert decode_refusal(MalformedPayload("junk")) is RefusalReason.BAD_REQUEST
    wrong = ErrorReply.make(ErrorCode.WRONG_ROBOT, "names robot-2")
    assert check_refusal(wrong) is RefusalReason.WRONG_ROBOT
    assert check_refusal(ErrorReply.make(ErrorCode.UNKNOWN_CUT, "cut 9")) is (
        RefusalReason.BAD_REQUEST
    )


def test_counts_snapshot_and_exit_summary(caplog: pytest.LogCaptureFixture) -> None:
    refusals = Refusals()
    caplog.set_level(logging.INFO, logger="cloudd.refusals")
    refusals.log_summary("edge-1")
    assert not caplog.records, "nothing refused, nothing logged"
    for reason in (RefusalReason.WRONG_ROBOT, RefusalReason.QUEUE_FULL, RefusalReason.WRONG_ROBOT):
        refusals.count(reason)
    assert refusals.get(RefusalReason.WRONG_ROBOT) == 2
    assert refusals.get(RefusalReason.ECHO_TOO_LARGE) == 0
    assert refusals.snapshot() == {"wrong_robot": 2, "queue_full": 1}
    refusals.log_summary("edge-1")
    assert caplog.messages == ["edge-1: refused (reason, count): wrong_robot 2, queue_full 1"]
