"""A robot whose frames arrive on their own measures its codecs on the first frames it serves: a
robot daemon (in a thread) with `source: zenoh` on real Zenoh on loopback, fed by the
application client (`robotd.results.client.RobotClient`).

Regression guard (issue 33): such a robot measured its codecs at start on scikit-image's
photographs, which a robot installed from the runtime lock does not have. What must hold: it
starts on raw actions; once `fidelity.calibration_frames` frames are served, the policy built on
the codecs measured on them takes over (the table cached); every frame sent has its result, the
ones around the switch included; the next start of the same robot reads the measurement back and
starts on it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from common import keys
from common.models import cache_dir, read_cached_json
from deploy.readiness import wait_until
from robotd.daemon import RobotDaemon
from robotd.policies import Policy
from robotd.results.client import RobotClient
from tests.helpers.onnx_graphs import camera_classifier, save
from tests.integration.conftest import Router
from tests.integration.test_robot_zenoh_io import RunningRobot
from tests.integration.test_robotd import FLEET, ROBOT, fleet_config

CALIBRATION_FRAMES = 3
SERVED_AFTER = 2
WAIT_S = 10.0


@pytest.fixture(scope="module")
def model_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # A size of its own: no other test's measurement of this model is in the session's cache.
    model = camera_classifier(height=24, width=24)
    return save(model, tmp_path_factory.mktemp("model") / "camera.onnx")


@pytest.fixture
def registry_token(zenoh_peer: zenoh.Session) -> Iterator[None]:
    """The registry's token only: the robot does not report the registry missing."""
    token = zenoh_peer.liveliness().declare_token(keys.alive_registry(FLEET, "registry"))
    yield
    token.undeclare()


def camera_frame(n: int) -> np.ndarray:
    """Frame `n`, BGR 48×48: smooth gradients and a square moving by n pixels, as a camera's."""
    y, x = np.mgrid[0:48, 0:48]
    image = np.stack([x * 4 + n, y * 4, (x + y) * 2], axis=-1).astype(np.uint8)
    image[10 + n : 24 + n, 14:28] = 220
    return image


def actions_of(policy: Policy) -> set[tuple[int, str]]:
    """The (cut, codec) actions a policy chooses among."""
    return set(zip(policy.cuts.indices, policy.cuts.codecs, strict=True))


def started(robot: RunningRobot) -> RobotDaemon:
    """The robot's daemon once its frame loop is made."""
    daemon = robot.daemon
    wait_until(lambda: daemon._started is not None, timeout_s=WAIT_S, what="the robot to start")
    return daemon


def test_codecs_measured_on_the_first_frames_served_then_read_back(
    zenoh_router: Router, model_file: Path, registry_token: None
) -> None:
    cfg = fleet_config(
        zenoh_router.endpoint,
        model_file,
        policy={"kind": "elastic"},
        fidelity={"calibration_frames": CALIBRATION_FRAMES},
    )
    robot = RunningRobot(cfg, policy="elastic")
    try:
        daemon = started(robot)
        first = daemon.policy
        assert set(first.cuts.codecs) == {"raw"}, "nothing but raw before any frame is measured"
        assert daemon.loop.refinement is not None
        with RobotClient(cfg, ROBOT) as client:
            assert client.wait_for_robot(WAIT_S), "the robot's zenoh source never subscribed"
            for n in range(CALIBRATION_FRAMES + SERVED_AFTER):
                sent = client.send(camera_frame(n))
                result = next(r for r in client.results(WAIT_S) if r.stamp_ns >= sent)
                assert result.stamp_ns == sent, f"frame {n} has no result of its own"
        assert daemon.policy is not first and daemon.loop.refinement is None
        (cached,) = (cache_dir() / "codecs").glob(f"{daemon.model.digest[:16]}-*.json")
        actions = {
            (int(k), e["name"])
            for k, entries in read_cached_json(cached).items()
            for e in entries
            if e["action"]
        }
        # The learner keeps the measured actions that some link speed can make the best.
        assert actions_of(daemon.policy) <= actions
    finally:
        robot.stop()
    again = RunningRobot(cfg, policy="elastic")
    try:
        daemon = started(again)
        assert daemon.loop.refinement is None, "the measurement is read back from the cache"
        assert actions_of(daemon.policy) <= actions
    finally:
        again.stop()
