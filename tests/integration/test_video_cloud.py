"""h264 frames against a real cloud daemon over Zenoh on loopback (started in-process): the
robot's request sender and video streams on one side, the deployment's decoders on the other.

What must hold: a stream's frames are answered with the model's outputs on exactly the picture
the robot's frame decodes to (the deployment's decoder is never ahead, behind or guessing); a
P-frame the deployment cannot decode (its decoder freed) is refused `need_keyframe`, and with a
keyframe to send the call resends the frame as one within its deadline and is answered
(`ResendReason.KEYFRAME`); corrupt or truncated h264, and a body claiming another robot, get
named error replies while the daemon keeps serving; a robot sent to standby has its decoder
freed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from cloudd.daemon import CloudDaemon
from cloudd.refusals import RefusalReason
from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.wire import ErrorCode, ErrorReply, decode
from common.wire.cloud_to_robot import INFER_REPLIES, InferReply
from common.wire.registry import CtlOp, CtlReply, CtlRequest
from common.wire.robot_to_cloud import InferRequest
from common.wire.telemetry import FallbackReason, ResendReason
from common.wire.tensor_codecs import EncodedTensor
from common.wire.video_codec import H264Decoder
from deploy.readiness import wait_until
from robotd.frame_path.request_sender import RequestSender
from robotd.frame_path.video_streams import VideoEncoders
from tests.helpers.onnx_graphs import camera_classifier, save
from tests.integration.conftest import Router, running_cloud
from tests.unit.test_video import camera

ROBOT = "robot-1"
SERVICE = "vision"
H, W = 48, 64
WAIT_S = 20.0
DEADLINE_S = 2.0


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(camera_classifier(H, W), tmp_path_factory.mktemp("model") / "camera.onnx")


@pytest.fixture(scope="module")
def reference(model_path: Path) -> SplitModel:
    return SplitModel(load_partition(str(model_path)), lazy=True)


def fleet_config(model: Path, endpoint: str) -> FleetConfig:
    return fleet_from_dict(
        {
            "fleet": "video",
            "service": SERVICE,
            "model": str(model),
            "registry": {"endpoint": endpoint, "listen": [endpoint]},
            "machines": {
                "edge-1": {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
                ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
            },
            "initial_policy": {"edge-1": "service"},
            "latency_bound": {"seconds": 0.5},
            "deadline_s": DEADLINE_S,
        }
    )


@pytest.fixture
def cloud(zenoh_router: Router, model_path: Path) -> Iterator[CloudDaemon]:
    with running_cloud(fleet_config(model_path, zenoh_router.endpoint), "edge-1", WAIT_S) as d:
        yield d


def answers(session: zenoh.Session, key: str, payload: bytes) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, payload=payload) if r.ok is not None]


def ctl(session: zenoh.Session, cloud: CloudDaemon, op: CtlOp, epoch: int) -> CtlReply:
    request = CtlRequest(op=op, robot=ROBOT, epoch=epoch, sender="test")
    key = keys.dep_ctl(cloud.cfg.fleet, "edge-1")
    got = wait_until(
        lambda: answers(session, key, request.to_wire()) or None, timeout_s=WAIT_S, what="ctl"
    )
    reply = decode(got[0])
    assert isinstance(reply, CtlReply) and reply.ok, reply
    return reply


def serve(session: zenoh.Session, cloud: CloudDaemon) -> None:
    """Put ROBOT in service and wait until its service key answers this session (a payload
    that is no request: refused unread, the decoders untouched)."""
    ctl(session, cloud, CtlOp.SERVICE, 1)
    key = keys.svc_infer(cloud.cfg.fleet, SERVICE, ROBOT)
    wait_until(
        lambda: answers(session, key, b"not a request") or None,
        timeout_s=WAIT_S,
        what="the service key",
    )


class Robot:
    """The robot's side: its video streams and request sender on a peer session."""

    def __init__(self, session: zenoh.Session, cloud: CloudDaemon, model: SplitModel) -> None:
        self.key = keys.svc_infer(cloud.cfg.fleet, SERVICE, ROBOT)
        self.sender = RequestSender(
            session,
            self.key,
            robot=ROBOT,
            model_digest=model.digest,
            deadline_s=DEADLINE_S,
            max_reply_bytes=1 << 20,
        )
        self.streams = VideoEncoders()
        self.frames = camera(12, height=H, width=W)
        self.n = 0

    def send(self, *, rekey: bool = True) -> tuple[Any, dict[str, EncodedTensor]]:
        n = self.n
        self.n += 1
        image = {"image": self.frames[n % len(self.frames)]}
        tensors, video = self.streams.encode(n, "edge-1", 1, image)
        sent: dict[str, EncodedTensor] = dict(tensors)

        def keyframe() -> tuple[dict[str, EncodedTensor], Any]:
            again, stream = self.streams.encode(n, "edge-1", 1, image, keyframe=True)
            sent.update(again)
            return again, stream

        call = self.sender.send(n, 0, tensors, 1, video=video, keyframe=keyframe if rekey else None)
        assert call.wait()
        return call, sent


def test_a_stream_is_answered_on_the_pictures_it_decodes_to_and_resent_as_a_keyframe(
    cloud: CloudDaemon,
    open_peer: Callable[..., zenoh.Session],
    reference: SplitModel,
) -> None:
    session = open_peer()
    serve(session, cloud)
    robot = Robot(session, cloud, reference)
    mirror = H264Decoder(H, W, 3)  # the deployment's decoder, replayed here
    for i in range(6):
        call, sent = robot.send()
        result = call.result()
        assert result.reply is not None, result.detail
        assert call.video.keyframe == (i == 0)
        picture = mirror.decode(bytes(sent["image"].data), keyframe=call.video.keyframe)
        want = reference.run_full({"image": picture[None]})
        np.testing.assert_allclose(result.reply.outputs["logits"], want["logits"], atol=1e-4)

    # The deployment freed its decoder (idle, or a flood of other robots): the P-frame is refused
    # need_keyframe and resent as a keyframe within the deadline.
    plane = cloud.plane(SERVICE)
    plane.video.forget(ROBOT)
    call, sent = robot.send()
    result = call.result()
    assert result.reply is not None, result.detail
    assert result.resends == (ResendReason.KEYFRAME,) and call.video.keyframe
    assert call.bytes_up > len(sent["image"].data)  # the P-frame and the keyframe
    picture = H264Decoder(H, W, 3).decode(bytes(sent["image"].data), keyframe=True)
    want = reference.run_full({"image": picture[None]})
    np.testing.assert_allclose(result.reply.outputs["logits"], want["logits"], atol=1e-4)
    assert cloud.refusals.get(RefusalReason.NEED_KEYFRAME) == 1

    # Without a keyframe to send, the refusal is the frame's answer (the robot finishes it).
    plane.video.forget(ROBOT)
    call, _ = robot.send(rekey=False)
    result = call.result()
    assert result.reply is None and result.reason is FallbackReason.ERROR
    assert result.detail.startswith(ErrorCode.NEED_KEYFRAME.value)

    # Standby frees the robot's decoder.
    call, _ = robot.send()
    assert call.result().reply is not None and ROBOT in plane.video.robots()
    ctl(session, cloud, CtlOp.STANDBY, 2)
    assert ROBOT not in plane.video.robots()


def test_corrupt_h264_and_a_stream_claiming_another_robot_are_named_refusals(
    cloud: CloudDaemon,
    open_peer: Callable[..., zenoh.Session],
    reference: SplitModel,
) -> None:
    session = open_peer()
    serve(session, cloud)
    robot = Robot(session, cloud, reference)
    frames = camera(2, height=H, width=W)
    tensors, video = robot.streams.encode(0, "edge-1", 1, {"image": frames[0]})
    data = bytes(tensors["image"].data)

    def ask(request: InferRequest) -> Any:
        replies = session.get(robot.key, payload=request.to_wire(), timeout=DEADLINE_S)
        return decode(
            next(r.ok.payload.to_bytes() for r in replies if r.ok is not None),
            expect=INFER_REPLIES,
        )

    def request(payload: bytes, **fields: Any) -> InferRequest:
        image = EncodedTensor(codec="h264", dtype="uint8", shape=[1, H, W, 3], data=payload)
        values: dict[str, Any] = {
            "robot": ROBOT,
            "frame": 1,
            "model_digest": reference.digest,
            "cut": 0,
            "tensors": {"image": image},
            "deadline_s": DEADLINE_S,
            "sent_at": 0.0,
            "epoch": 1,
            "video": video,
        }
        values.update(fields)
        return InferRequest(**values)

    for bad in (data[: len(data) // 2], bytes(range(256)) * 4, data + data):
        reply = ask(request(bad))
        assert isinstance(reply, ErrorReply) and reply.error_code is ErrorCode.CORRUPT_PAYLOAD
    other = ask(request(data, robot="robot-2"))
    assert isinstance(other, ErrorReply) and other.error_code is ErrorCode.WRONG_ROBOT
    # The deployment is up and the stream starts again from a good keyframe.
    assert isinstance(ask(request(data)), InferReply)
    assert cloud.refusals.get(RefusalReason.WRONG_ROBOT) == 1
