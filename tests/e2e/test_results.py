"""Frames in, results out, end to end: registry, two cloud daemons and a robot with `source:
zenoh` as real subprocesses; the application client (`robotd.results.client.RobotClient`) in this
process feeds frames from a real photograph; `elasticfog results --json` runs as a subprocess
beside it.

What must hold: frames are served by the cloud, then (both deployments killed) by the robot,
and every result says so; each result's stamp is the one the client sent; its outputs (in the
robot's result codec, fp16) equal onnxruntime's output of the whole model on the same decoded,
fitted image within fp16's rounding; `elasticfog results --json` prints one parseable object
per frame with those stamps and paths, and ends cleanly on SIGINT.
"""

from __future__ import annotations

import json
import signal
from typing import Any

import numpy as np
import pytest

from common.image_input import ImageInputs
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.photos import photo_bgr
from common.wire.app_to_robot import FrameIn, ImageIn, decode_image, image_in
from common.wire.robot_to_app import FP16_RELATIVE_ERROR, ServedBy
from deploy.readiness import wait_until
from robotd.results.cli import top_k
from robotd.results.client import Result, RobotClient
from robotd.sources.frame_sources import MAX_SOURCE_SIDE_PX, fit_frame
from tests.e2e.conftest import TEST_INPUT_SHAPE, TEST_MODEL

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
WAIT_S = 30.0
FRAME_TIMEOUT_S = 5.0
TOLERANCE = 1e-4
FRAMES_PER_PATH = 3
# A real photograph at a camera's size (the robot fits it to the model's 64×64 input).
CAMERA_H, CAMERA_W = 480, 640
# The client's stamps: a clock of the test's own, so equality with what comes back means the
# robot carried them through.
FIRST_STAMP_NS = 1_600_000_000_000_000_000


def camera_frame(n: int) -> np.ndarray:
    """Frame `n`: a 640×480 view of a real photograph, moved by n pixels."""
    photo = photo_bgr("astronaut")  # 512×512
    big = np.pad(photo, ((0, CAMERA_H), (0, CAMERA_W), (0, 0)), mode="reflect")
    return np.ascontiguousarray(big[n : n + CAMERA_H, n : n + CAMERA_W])


def served_until(
    client: RobotClient, path: ServedBy, frames: dict[int, ImageIn], count: int
) -> list[Result]:
    """Send frames (JPEG, stamped with a clock of our own) until `count` in a row were served
    by `path` (bounded by WAIT_S); `frames` keeps each image sent by its stamp."""
    got: list[Result] = []

    def one_more() -> bool:
        n = len(frames)
        image = image_in(camera_frame(n), "jpeg")
        stamp = client.send(FrameIn(stamp_ns=FIRST_STAMP_NS + n, images={"image": image}))
        frames[stamp] = image
        try:
            result = next(r for r in client.results(FRAME_TIMEOUT_S) if r.stamp_ns == stamp)
        except StopIteration:
            return False
        if result.served_by is path:
            got.append(result)
        else:
            got.clear()
        return len(got) >= count

    wait_until(one_more, timeout_s=WAIT_S, what=f"{count} frames served by the {path.value}")
    return got


def test_results_from_the_cloud_then_the_robot_with_the_senders_stamps(
    make_fleet: Any, local_fleet: Any
) -> None:
    fleet = make_fleet(machines={ROBOT: {"source": "zenoh", "results": {"codec": "fp16"}}})
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1", "edge-2"])
    lf.start_robot(ROBOT, "--policy", "cloud", wait=True)
    follower = lf.procs.start(
        "results", ["results", "--config", str(fleet.config), "--robot", ROBOT, "--json"]
    )
    wait_until(
        lambda: "following" in follower.log_text(),
        timeout_s=WAIT_S,
        what="elasticfog results to subscribe",
        procs=[follower],
    )
    model = SplitModel(load_partition(TEST_MODEL, input_shape=tuple(TEST_INPUT_SHAPE)))
    inputs = ImageInputs(model.input_specs())
    sent: dict[int, ImageIn] = {}
    with RobotClient(fleet.config, ROBOT) as client:
        assert client.wait_for_robot(WAIT_S), "the robot's zenoh source never subscribed"
        by_cloud = served_until(client, ServedBy.CLOUD, sent, FRAMES_PER_PATH)
        lf.kill("edge-1")
        lf.kill("edge-2")
        by_robot = served_until(client, ServedBy.ROBOT, sent, FRAMES_PER_PATH)
    for result in by_cloud + by_robot:
        fit = (inputs.height, inputs.width)
        bgr = decode_image(sent[result.stamp_ns], max_side_px=MAX_SOURCE_SIDE_PX, fit=fit)
        want = model.run_full(inputs.feeds(fit_frame(bgr, inputs.height, inputs.width)))
        for name, value in want.items():
            # The results travel in fp16: within its rounding, on top of the model's tolerance.
            assert result.message.outputs[name].codec == "fp16"
            np.testing.assert_allclose(
                result.outputs[name], value, rtol=FP16_RELATIVE_ERROR, atol=TOLERANCE
            )
    assert all(r.message.deployment in ("edge-1", "edge-2") for r in by_cloud)
    assert all(r.message.deployment is None for r in by_robot)

    # `elasticfog results --json`: Ctrl-C ends it with exit code 0; one object per line.
    stopped = follower.stop(sig=signal.SIGINT)
    assert stopped.returncode == 0 and not stopped.killed
    printed = [
        json.loads(line) for line in follower.log_text().splitlines() if line.startswith("{")
    ]
    by_stamp = {p["stamp_ns"]: p for p in printed}
    assert set(by_stamp) <= set(sent)
    for result in by_cloud + by_robot:
        line = by_stamp[result.stamp_ns]
        assert line["served_by"] == result.served_by.value and line["frame"] == result.frame
        assert line["robot"] == ROBOT and line["action"] == result.message.action
        for name, array in result.outputs.items():
            shown = line["outputs"][name]
            assert shown["shape"] == list(array.shape)
            top = top_k(array)
            assert shown["top5"] == (
                None if top is None else [[list(p) for p in row] for row in top]
            )
