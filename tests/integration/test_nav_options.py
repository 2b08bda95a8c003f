"""The navigation assistant's offloading options 1–4 on the real daemons, over Zenoh on loopback.

A registry, a cloud daemon serving zoo:stereo at 160×120 (D = 32; split with segments) and one
robot daemon per run, each fed the same rendered stereo frames (`stereo:world`, seeded):
option 1 sends the pair and the cloud runs everything, option 2 sends the points, option 3 sends
the pair and gets the points back (a segment; the robot runs d_coll from them), option 4 runs
everything on the robot; options 1 and 3 also run with the pair coded (`option:1:jpeg80`,
`option:3:png`: the cloud decodes the coded pair for a suffix and for a segment request). What
must hold: no frame lost, every offloaded frame answered by the cloud, the action label naming
the segment and the codec, and each frame's d_coll equal (float tolerance) to the all-robot one
on the same frame when the pair crossed losslessly (raw, PNG); under JPEG, d_coll with the
model's bins. A last run is `elastic`, which learns over the segments too: it explores one,
unhedged, and the cloud answers it with the end cut's tensors.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.config import FleetConfig, fleet_from_dict
from common.wire.telemetry import parse_action_codec
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from robotd.telemetry import SERVED_BY_CLOUD, SERVED_BY_ROBOT
from tests.helpers.registry import LEASE_MS, TEST_PARAMS, RunningRegistry
from tests.integration.conftest import find_free_port, loopback_endpoint, running_cloud

SERVICE = "nav"
DEPLOYMENT = "edge-1"
RUNS = {
    "1": "option:1",
    "2": "option:2",
    "3": "option:3",
    "4": "option:4",
    "1:jpeg80": None,
    "3:png": "option:3:png",
    "elastic": "elastic",
}
"""Run → the robot's `--policy`; None takes the fleet file's (`static`, option 1 with jpeg80)."""
ELASTIC_FRAMES = 12
"""elastic's run: enough for its first exploring frames (the segments' MB-returned feature is
unknown at first, so their confidence bonus is the largest)."""
ROBOTS = {run: f"robot-{run.replace(':', '-')}" for run in RUNS}
ALL_ROBOT = "4"
LOSSLESS = ("1", "2", "3", "3:png")
"""The runs whose crossings are exact, so d_coll equals the all-robot one."""
LOSSLESS_CODECS = ("raw", "raw+zstd", "png")
"""The pair's and the cuts' codecs that leave d_coll exact."""
DCOLL_BINS = 41
"""zoo:stereo's curvature bins (`nav.bins.count`)."""
FRAMES = 4
SOURCE = "stereo:world"
INPUT_SHAPE = [3, 120, 160]
DEADLINE_S = 5.0
"""Generous: the test is about equal results and no lost frame, not about speed (2 busy cores)."""
WAIT_S = 30.0
"""Bound of each wait for a daemon to start (the first start splits and verifies the model)."""
DCOLL_ATOL_M = 1e-5
"""d_coll is metres in float32; every cut and segment verifies with error 0, so this is slack."""
EXPECTED_ACTIONS = {
    "1": "cut:0",
    "2": "cut:4",
    "3": "cut:0-4",
    "4": "P",
    "1:jpeg80": "cut:0:jpeg80",
    "3:png": "cut:0-4:png",
}
"""zoo:stereo at 160×120 has cuts 0 (the pair) … 4 (points)."""


def fleet_config(folder: Path) -> FleetConfig:
    """The fleet; the registry's RIB file goes in `folder`, not the working directory."""
    endpoint = loopback_endpoint(find_free_port())
    robots = {robot: {"role": "robot", "source": SOURCE} for robot in ROBOTS.values()}
    data: dict[str, Any] = {
        "fleet": f"nav-{uuid.uuid4().hex[:8]}",
        "service": SERVICE,
        "model": "zoo:stereo",
        "input_shape": INPUT_SHAPE,
        "cuts": {"segments": True},
        "registry": {
            "endpoint": endpoint,
            "listen": [endpoint],
            "db": str(folder / "rib.sqlite"),
        },
        "machines": {DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]}, **robots},
        "initial_policy": {DEPLOYMENT: "service", **dict.fromkeys(ROBOTS.values(), "robot")},
        "latency_bound": {"stat": "median", "seconds": DEADLINE_S},
        "deadline_s": DEADLINE_S,
        "policy": {"kind": "static", "params": {"option": 1, "codec": "jpeg80"}},
        "zenoh": {"lease_ms": LEASE_MS},
    }
    return fleet_from_dict(data)


@pytest.fixture(scope="module")
def results(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[dict[str, list[FrameResult]]]:
    """Each run's frames, run against one registry and one cloud daemon."""
    cfg = fleet_config(tmp_path_factory.mktemp("nav-fleet"))
    registry = RunningRegistry(cfg, params=TEST_PARAMS).start()
    try:
        with running_cloud(cfg, DEPLOYMENT, WAIT_S):
            by_run: dict[str, list[FrameResult]] = {}
            for run, spec in RUNS.items():
                frames: list[FrameResult] = []
                daemon = RobotDaemon(
                    cfg,
                    ROBOTS[run],
                    RobotOptions(
                        frames=ELASTIC_FRAMES if run == "elastic" else FRAMES,
                        policy=spec,
                        registry_wait_s=WAIT_S,
                        route_wait_s=WAIT_S,
                    ),
                    on_result=frames.append,
                )
                assert daemon.run() == 0
                by_run[run] = frames
            yield by_run
    finally:
        registry.stop()


@pytest.mark.parametrize("run", [run for run in RUNS if run in EXPECTED_ACTIONS])
def test_no_frame_is_lost_and_the_cloud_answers_each_offload(
    results: dict[str, list[FrameResult]], run: str
) -> None:
    frames = results[run]
    assert sorted(r.frame for r in frames) == list(range(FRAMES))
    for r in frames:
        assert r.record.action == EXPECTED_ACTIONS[run]
        assert not r.record.fallback, f"run {run} frame {r.frame}: {r.record.detail}"
        served = SERVED_BY_ROBOT if run == ALL_ROBOT else SERVED_BY_CLOUD
        assert r.served_by == served


@pytest.mark.parametrize("run", LOSSLESS)
def test_dcoll_of_each_lossless_run_equals_the_all_robot_one(
    results: dict[str, list[FrameResult]], run: str
) -> None:
    robot_only = {r.frame: r for r in results[ALL_ROBOT]}
    for r in results[run]:
        same = robot_only[r.frame]
        for view in ("left", "right"):  # the same frame went in
            np.testing.assert_array_equal(r.feeds[view], same.feeds[view])
        assert sorted(r.outputs) == ["d_coll"]
        np.testing.assert_allclose(
            r.outputs["d_coll"], same.outputs["d_coll"], rtol=0, atol=DCOLL_ATOL_M
        )


def test_a_jpeg_pair_gives_dcoll_with_the_model_bins(
    results: dict[str, list[FrameResult]],
) -> None:
    """JPEG is lossy: the disparities, hence d_coll, may differ from the raw pair's; the shape
    and finite distances must not."""
    for r in results["1:jpeg80"]:
        assert sorted(r.outputs) == ["d_coll"]
        d_coll = np.asarray(r.outputs["d_coll"])
        assert d_coll.shape == (1, DCOLL_BINS) and np.isfinite(d_coll).all()


def test_the_coded_pair_is_smaller_than_the_raw_one(
    results: dict[str, list[FrameResult]],
) -> None:
    """The codec is applied on the wire, not only named in the label."""
    raw = min(r.record.bytes_up for r in results["1"])
    assert max(r.record.bytes_up for r in results["1:jpeg80"]) < raw / 2
    assert max(r.record.bytes_up for r in results["3:png"]) < raw


def test_the_segment_reply_carried_the_points(results: dict[str, list[FrameResult]]) -> None:
    """Option 3's reply is the points (1×H×W×3 float32), far bigger than d_coll's 164 bytes."""
    height, width = INPUT_SHAPE[1:]
    points_bytes = height * width * 3 * 4
    for run in ("3", "3:png"):
        for r in results[run]:
            assert r.record.bytes_down > points_bytes
    for r in results["1"]:
        assert r.record.bytes_down < points_bytes


def test_elastic_explores_a_segment_unhedged_and_the_cloud_answers_it(
    results: dict[str, list[FrameResult]],
) -> None:
    """The learner's actions include the split's segments (`cuts.segments`): one is explored,
    never hedged, answered by the cloud with its end cut's tensors, the robot finishing the
    frame from them; no frame lost, and d_coll exact where the crossing was lossless (the
    calibration on a few frames may admit a lossy codec: then d_coll with the model's bins)."""
    frames = results["elastic"]
    assert sorted(r.frame for r in frames) == list(range(ELASTIC_FRAMES))
    segments = [r for r in frames if "-" in r.record.action]
    assert segments, [r.record.action for r in frames]
    robot_only = {r.frame: r for r in results[ALL_ROBOT]}
    for r in segments:
        assert not r.hedged and not r.record.fallback, r.record.detail
        assert r.served_by == SERVED_BY_CLOUD
        assert r.record.bytes_down > DCOLL_BINS * 4
    for r in frames:
        d_coll = np.asarray(r.outputs["d_coll"])
        assert d_coll.shape == (1, DCOLL_BINS) and np.isfinite(d_coll).all()
        lossless = parse_action_codec(r.record.action)[1] in LOSSLESS_CODECS
        if r.frame in robot_only and lossless:
            np.testing.assert_allclose(
                d_coll, robot_only[r.frame].outputs["d_coll"], rtol=0, atol=DCOLL_ATOL_M
            )
