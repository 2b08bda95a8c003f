"""Round-robin pools with real daemons (`dispatch: round_robin`): the registry puts a pool of
deployments in service for a robot, the robot sends each frame to one member in turn, a killed
member is dropped and a standby joins, no frame is lost and none is computed twice."""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from common import keys
from common.wire import decode
from common.wire.registry import ProbeReply, ProbeRequest
from deploy.demo_summary import answered_by, read_telemetry
from deploy.procs import elasticfog_argv

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
FRAMES = 160
WAIT_S = 30.0
SHARED = 20
"""Frames each of the first pool's members answers before one of them is killed."""
CLOUDS = ("edge-1", "edge-2", "edge-3")


def _served(lf: Any, fleet: str, deployment: str) -> int:
    """Frames the deployment says it computed for the robot (its probe reply)."""
    request = ProbeRequest(sender="pool-test", sent_at=time.time())
    for reply in lf.session.get(
        keys.dep_probe(fleet, deployment), payload=request.to_wire(), timeout=5.0
    ):
        if reply.ok is not None:
            return decode(reply.ok.payload.to_bytes(), expect=ProbeReply).served.get(ROBOT, 0)
    raise AssertionError(f"{deployment} did not answer its probe")


def test_a_pool_shares_frames_survives_a_killed_member_and_computes_each_frame_once(
    make_fleet, local_fleet, tmp_path: Path
) -> None:
    fleet = make_fleet(
        dispatch={"mode": "round_robin", "pool_size": 2},
        machines={
            "edge-3": {"role": "cloud", "listen": ["tcp/127.0.0.1:0"], "workers": 1},
            ROBOT: {"fps": 25.0},
        },
    )
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(list(CLOUDS))
    tap = lf.tap(ROBOT)
    telemetry = tmp_path / "robot-1.jsonl"
    robot = lf.start_robot(
        ROBOT, "--policy", "cloud", "--max-in-flight", "2", frames=FRAMES, telemetry=telemetry
    )

    # edge-1 is the serving deployment (initial_policy); edge-2 ranks first of the others.
    def both_serve(records: list[dict[str, Any]]) -> bool:
        by = Counter(answered_by(r) for r in records)
        return by["edge-1"] >= SHARED and by["edge-2"] >= SHARED

    tap.wait_for(
        lambda r: both_serve(tap.snapshot()), timeout_s=WAIT_S, what="a pool of 2", procs=[robot]
    )
    killed_at = time.time()
    lf.latest("edge-2").send_signal(signal.SIGKILL)
    tap.wait_for(
        lambda r: r["at"] > killed_at and answered_by(r) == "edge-3",
        timeout_s=WAIT_S,
        what="edge-3 joining the pool after edge-2 was killed",
        procs=[robot],
    )
    assert robot.wait(60.0) == 0, robot.log_tail()

    records = read_telemetry(telemetry)
    frames = [r["frame"] for r in records]
    assert sorted(frames) == list(range(FRAMES)), "a frame is missing or reported twice"
    by = Counter(answered_by(r) for r in records)
    # While the pool was edge-1 + edge-2 the two shared the frames in turn.
    before = [answered_by(r) for r in records if r["at"] < killed_at and answered_by(r)]
    assert before, "no frame answered before the kill"
    share = Counter(before)
    assert abs(share["edge-1"] - share["edge-2"]) <= max(4, len(before) // 5), share
    assert by["edge-3"] > 0 and by["edge-1"] > 0
    # Frames whose member died were finished on the robot: counted, not lost.
    fallbacks = Counter(r.get("reason") for r in records if r.get("fallback"))
    assert sum(fallbacks.values()) < FRAMES // 4, fallbacks

    # Each frame once: what the live members computed is what they answered (a reply too late
    # for its deadline is computed but finished on the robot: at most the timeouts).
    for member in ("edge-1", "edge-3"):
        served = _served(lf, fleet.name, member)
        assert by[member] <= served <= by[member] + fallbacks.get("timeout", 0), (member, served)
    registry_log = lf.latest("registry").log_text()
    assert "pool edge-1, edge-3" in registry_log, registry_log[-2000:]
    # The routing-state CLI shows the pool.
    routes = subprocess.run(
        [*elasticfog_argv(), "routes", "--config", str(lf.config), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert routes.returncode == 0, routes.stderr
    [route] = [r for r in json.loads(routes.stdout) if r["robot"] == ROBOT]
    assert (route["deployment"], route["pool"]) == ("edge-1", ["edge-1", "edge-3"]), route
