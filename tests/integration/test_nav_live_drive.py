"""A maneuver of the navigation circuit driven live by the real robot daemon, over Zenoh on
loopback (`stereo:maneuver:N`, `nav.maneuver_source`).

A registry, a cloud daemon serving zoo:stereo at 160×120 (D = 32) and a robot daemon running
option 1 (the pair to the cloud, d_coll back) at the paper's 10 fps camera, with no frame limit:
the source ends the run when the maneuver is over. Maneuver 1 (full speed at a wall 1.2 m
ahead, 4 s) is the shortest; the in-process loop stops short of the wall with the assistant and
hits it without (at 2.52 s). What must hold: the run stops by itself and writes its outcome
file, the assisted run does not collide and the unassisted one does, every frame read got its
result (none lost, each answered by the cloud), and the assistant applied the d_coll values.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from common.config import FleetConfig, fleet_from_dict
from nav.live_drive import read_outcome
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from robotd.telemetry import SERVED_BY_CLOUD
from tests.helpers.registry import LEASE_MS, TEST_PARAMS, RunningRegistry
from tests.integration.conftest import find_free_port, loopback_endpoint, running_cloud

SERVICE = "nav"
DEPLOYMENT = "edge-1"
ROBOT = "robot-1"
MANEUVER = 1
INPUT_SHAPE = [3, 120, 160]
FPS = 10.0
MAX_FRAMES = 200
"""A bound far above the maneuver's ~45 frames: a source that never ended fails the outcome
check instead of hanging the test."""
DEADLINE_S = 5.0
WAIT_S = 30.0
"""Bound of each wait for a daemon to start (the first start splits and verifies the model)."""


def fleet_config(folder: Path) -> FleetConfig:
    endpoint = loopback_endpoint(find_free_port())
    data: dict[str, Any] = {
        "fleet": f"navlive-{uuid.uuid4().hex[:8]}",
        "service": SERVICE,
        "model": "zoo:stereo",
        "input_shape": INPUT_SHAPE,
        "registry": {
            "endpoint": endpoint,
            "listen": [endpoint],
            "db": str(folder / "rib.sqlite"),
        },
        "machines": {
            DEPLOYMENT: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
            ROBOT: {"role": "robot", "source": "stereo:world"},
        },
        "initial_policy": {DEPLOYMENT: "service", ROBOT: "robot"},
        "latency_bound": {"stat": "median", "seconds": DEADLINE_S},
        "deadline_s": DEADLINE_S,
        "policy": {"kind": "static", "params": {"option": 1}},
        "zenoh": {"lease_ms": LEASE_MS},
    }
    return fleet_from_dict(data)


class Run:
    """One robot run of the maneuver: its results, frames and outcome."""

    def __init__(self, cfg: FleetConfig, folder: Path, assist: bool) -> None:
        self.out = folder / f"outcome-{'on' if assist else 'off'}.json"
        spec = f"stereo:maneuver:{MANEUVER}:assist={'on' if assist else 'off'}:out={self.out}"
        self.results: list[FrameResult] = []
        self.daemon = RobotDaemon(
            cfg,
            ROBOT,
            RobotOptions(
                source=spec,
                frames=MAX_FRAMES,
                fps=FPS,
                registry_wait_s=WAIT_S,
                route_wait_s=WAIT_S,
            ),
            on_result=self.results.append,
        )
        self.code = self.daemon.run()
        self.outcome = read_outcome(self.out) if self.out.exists() else None


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[bool, Run]]:
    """The maneuver with the assistant on and off, against one registry and one cloud."""
    folder = tmp_path_factory.mktemp("nav-live")
    cfg = fleet_config(folder)
    registry = RunningRegistry(cfg, params=TEST_PARAMS).start()
    try:
        with running_cloud(cfg, DEPLOYMENT, WAIT_S):
            yield {assist: Run(cfg, folder, assist) for assist in (True, False)}
    finally:
        registry.stop()


@pytest.mark.parametrize("assist", [True, False], ids=["assisted", "unassisted"])
def test_the_run_ends_with_the_maneuver_and_writes_its_outcome(
    runs: dict[bool, Run], assist: bool
) -> None:
    run = runs[assist]
    assert run.code == 0
    assert run.outcome is not None, f"no outcome file {run.out}"
    assert run.outcome["maneuver_index"] == MANEUVER and run.outcome["assisted"] is assist
    assert run.daemon.frames_done < MAX_FRAMES  # the source ended the run


@pytest.mark.parametrize("assist", [True, False], ids=["assisted", "unassisted"])
def test_no_frame_is_lost_and_the_cloud_answers_each(runs: dict[bool, Run], assist: bool) -> None:
    run = runs[assist]
    assert run.outcome is not None
    frames = run.daemon.frames_done
    assert frames == run.outcome["frames_read"]
    assert sorted(r.frame for r in run.results) == list(range(frames))
    for r in run.results:
        assert r.record.action == "cut:0"
        assert r.served_by == SERVED_BY_CLOUD, f"frame {r.frame}: {r.record.detail}"


def test_the_assistant_keeps_the_robot_off_the_wall_it_hits_without(
    runs: dict[bool, Run],
) -> None:
    assisted, unassisted = runs[True].outcome, runs[False].outcome
    assert assisted is not None and unassisted is not None
    assert unassisted["collided"] and unassisted["frames_applied"] == 0
    assert not assisted["collided"], assisted  # the control thread's lag is in the outcome
    assert assisted["min_clearance_m"] > 0 and assisted["distance_m"] > 0.5
    assert assisted["frames_applied"] > 10 and assisted["mean_dcoll_age_s"] > 0
