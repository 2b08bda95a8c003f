"""Result sinks of the robot daemon (`robotd.results.sinks`) on a real run over loopback Zenoh:
every applied frame reaches every sink once, in frame order, with its capture stamp; a sink that
fails does not stop the frame loop (regression guard: a publisher's error must never end a run);
every sink is closed at shutdown and taken off the daemon's list."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from common import keys
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from robotd.results.sinks import ResultSink
from tests.helpers.onnx_graphs import save
from tests.integration.conftest import Router
from tests.integration.test_robotd import (
    FLEET,
    FRAMES,
    ROBOT,
    WAIT_S,
    fleet_config,
    tiny_conv_model,
)


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save(tiny_conv_model(), tmp_path_factory.mktemp("model") / "tiny.onnx")


@pytest.fixture
def fake_registry(zenoh_peer: zenoh.Session) -> Iterator[zenoh.Session]:
    """The registry's token only: the robot does not report the registry missing."""
    token = zenoh_peer.liveliness().declare_token(keys.alive_registry(FLEET, "registry"))
    yield zenoh_peer
    token.undeclare()


class RecordingSink:
    def __init__(self) -> None:
        self.results: list[FrameResult] = []
        self.closed = 0

    def publish(self, result: FrameResult) -> None:
        self.results.append(result)

    def close(self) -> None:
        self.closed += 1


class FailingSink(RecordingSink):
    def publish(self, result: FrameResult) -> None:
        super().publish(result)
        raise RuntimeError("this sink always fails")


def test_every_applied_frame_reaches_every_sink_and_sinks_close_at_shutdown(
    zenoh_router: Router, model_file: Path, fake_registry: zenoh.Session
) -> None:
    cfg = fleet_config(zenoh_router.endpoint, model_file)
    seen: list[FrameResult] = []
    daemon = RobotDaemon(
        cfg,
        ROBOT,
        RobotOptions(frames=FRAMES, policy="robot", registry_wait_s=WAIT_S, route_wait_s=0.1),
        on_result=seen.append,
    )
    failing, recording = FailingSink(), RecordingSink()
    assert isinstance(recording, ResultSink)
    daemon.add_result_sink(failing, "failing sink")
    daemon.add_result_sink(recording, "recording sink")
    assert daemon.result_sinks == (failing, recording)
    assert daemon.run() == 0
    assert [r.frame for r in recording.results] == list(range(FRAMES))
    assert [r.frame for r in failing.results] == list(range(FRAMES))
    assert [r.stamp_ns for r in recording.results] == [r.stamp_ns for r in seen]
    assert all(r.stamp_ns > 0 for r in recording.results)
    assert failing.closed == recording.closed == 1
    assert daemon.result_sinks == ()
    assert daemon.summary.frames == FRAMES
