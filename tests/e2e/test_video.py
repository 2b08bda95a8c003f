"""Video crossings end to end (issue 34's must-show): registry, two cloud daemons and a robot as
real subprocesses on loopback, the robot's camera a 640×480 view moving over a real photograph
(scikit-image's astronaut, the `photo` source: nothing of ours in the picture), its uplink paced
at 2 Mbit/s (`--uplink-mbit 2`).

What must hold:
- `cloud:h264` against `cloud:jpeg50` on the same frames: h264 sends a keyframe first, then
  P-frames far smaller than JPEG 50's frames, and its mean latency is lower; every frame of
  both is answered by the cloud, and the outputs (read on `out/<robot>` with the results
  client) agree with a robot-only run of the same frames (top-1, and within a small relative
  error);
- killing the deployment serving an h264 run in its middle loses no frame: every frame has a
  result, none finished on the robot, the other deployment serves the rest and its first frame
  is a keyframe (a fresh decoder never gets a P-frame it cannot decode).
The measured figures are printed (`pytest -s`) and quoted in docs/video.md.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.readiness import wait_until
from robotd.results.client import RobotClient
from tests.e2e.conftest import Fleet
from tests.helpers.onnx_graphs import camera_classifier, save

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
FRAMES = 30
FPS = 10.0
UPLINK_MBIT = "2"
SOURCE = "photo:astronaut,motion=pan"
WAIT_S = 60.0
CLASSES = 8
# A lossy crossing moves the logits a little; the answer (top-1) must not move.
MAX_REL_ERR = 0.05


def video_fleet(make_fleet: Any, tmp_path: Path) -> Fleet:
    """A fleet whose model takes the 640×480 camera image (cheap: the crossing is under test)."""
    model = save(camera_classifier(480, 640, CLASSES), tmp_path / "camera.onnx")
    fleet: Fleet = make_fleet(
        model=str(model),
        input_shape=None,
        deadline_s=1.0,
        machines={ROBOT: {"fps": FPS}},
    )
    return fleet


def run(lf: Any, fleet: Fleet, policy: str, telemetry: Path, kill_at: int | None = None) -> Any:
    """One robot run of FRAMES frames; (telemetry records, outputs by frame, the kill's victim)."""
    killed = None
    with RobotClient(fleet.config, ROBOT, max_queued=4 * FRAMES) as client:
        robot = lf.start_robot(
            ROBOT,
            "--policy",
            policy,
            "--source",
            SOURCE,
            "--uplink-mbit",
            UPLINK_MBIT,
            frames=FRAMES,
            telemetry=telemetry,
        )
        if kill_at is not None:

            def serving() -> str | None:
                lines = telemetry.read_text().splitlines() if telemetry.exists() else []
                return json.loads(lines[-1])["deployment"] if len(lines) >= kill_at else None

            killed = wait_until(serving, timeout_s=WAIT_S, what=f"frame {kill_at}", procs=[robot])
            lf.kill(killed)
        assert robot.wait(WAIT_S) == 0, robot.log_tail(20)
        outputs = {r.frame: r.outputs for r in client.results(timeout=2.0)}
    records = [json.loads(line) for line in telemetry.read_text().splitlines()]
    return records, outputs, killed


def agree(outputs: dict[int, Any], reference: dict[int, Any]) -> tuple[float, float]:
    """(share of frames whose top-1 class is the reference's, largest relative error)."""
    same, worst = [], 0.0
    for frame, out in outputs.items():
        got, want = out["logits"], reference[frame]["logits"]
        same.append(int(got.argmax()) == int(want.argmax()))
        worst = max(worst, float(np.linalg.norm(got - want) / np.linalg.norm(want)))
    return float(np.mean(same)), worst


def test_h264_against_jpeg50_at_2_mbit_agrees_with_the_robot(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    fleet = video_fleet(make_fleet, tmp_path)
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1", "edge-2"])
    _, robot_only, _ = run(lf, fleet, "robot", tmp_path / "robot.jsonl")
    assert sorted(robot_only) == list(range(FRAMES))
    rows = {}
    for policy in ("cloud:jpeg50", "cloud:h264"):
        records, outputs, _ = run(lf, fleet, policy, tmp_path / f"{policy[6:]}.jsonl")
        assert len(records) == FRAMES and sorted(outputs) == list(range(FRAMES))
        assert all(not r["fallback"] and r["served_by"] == "cloud" for r in records)
        top1, rel_err = agree(outputs, robot_only)
        assert top1 == 1.0 and rel_err < MAX_REL_ERR, (policy, top1, rel_err)
        rows[policy] = {
            "median_bytes": statistics.median(r["bytes_up"] for r in records),
            "max_bytes": max(r["bytes_up"] for r in records),
            "mean_latency_ms": 1000 * statistics.mean(r["latency_s"] for r in records),
            "p95_latency_ms": 1000 * float(np.percentile([r["latency_s"] for r in records], 95)),
            "keyframes": sum(bool(r["keyframe"]) for r in records),
            "top1": top1,
            "rel_err": rel_err,
        }
    print(json.dumps(rows, indent=1))
    h264, jpeg = rows["cloud:h264"], rows["cloud:jpeg50"]
    assert 1 <= h264["keyframes"] <= 2  # the first frame (and the first after the route is known)
    assert h264["median_bytes"] * 3 < jpeg["median_bytes"]
    assert h264["mean_latency_ms"] < jpeg["mean_latency_ms"]


def test_killing_the_serving_deployment_mid_h264_loses_no_frame(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    fleet = video_fleet(make_fleet, tmp_path)
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1", "edge-2"])
    kill_at = FRAMES // 2
    records, outputs, killed = run(
        lf, fleet, "cloud:h264", tmp_path / "failover.jsonl", kill_at=kill_at
    )
    assert sorted(r["frame"] for r in records) == list(range(FRAMES))
    assert sorted(outputs) == list(range(FRAMES))  # no frame lost
    survivor = ({"edge-1", "edge-2"} - {killed}).pop()
    after = [r for r in records if r["deployment"] == survivor]
    assert after, "the other deployment served nothing"
    first = min(after, key=lambda r: r["frame"])
    assert first["keyframe"] is True  # a fresh decoder starts from a keyframe
    # Every frame after the survivor's first is answered by it (none finished on the robot).
    assert all(r["deployment"] == survivor for r in records if r["frame"] >= first["frame"])
    print(
        json.dumps(
            {
                "killed": killed,
                "at_frame": kill_at,
                "survivor_first_frame": first["frame"],
                "fallbacks": [r["frame"] for r in records if r["fallback"]],
                "resends": {r["frame"]: r["resends"] for r in records if r["resends"]},
            }
        )
    )
