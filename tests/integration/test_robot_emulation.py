"""The robot daemon's emulation hooks (robotd/emulation.py) in its real frame loop, over a real
Zenoh session on loopback: `--phases` switch the robot slowdown at their first frame, every
robot-side model run is stretched by it, and each frame's telemetry line names its phase.

No deployment and no registry: the `robot` policy computes every frame on the robot, which is
what the slowdown acts on (the uplink phases are checked end to end in tests/e2e).
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, numpy_helper

from common.config import fleet_from_dict
from common.errors import UserError
from robotd.daemon import RobotDaemon, RobotOptions
from robotd.emulation import Phase
from tests.helpers.onnx_graphs import make_model, node, save, vi
from tests.integration.conftest import Router

ROBOT = "robot-1"
INPUT_SHAPE = (1, 3, 96, 96)
CHANNELS = 64
FRAMES_PER_PHASE = 6
SLOWDOWN = 6.0
MIN_RATIO = 2.5
"""Median frame time of the slowed phases over the others: 6 emulated, at least 2.5 observed
(the frame loop's own work outside the model runs is not stretched, and the host is shared:
the phases alternate so that a busy spell falls on both kinds)."""


def conv_model() -> onnx.ModelProto:
    """image[1,3,96,96] → Conv(64) → Relu → Conv(64) → Relu → GAP → Flatten: some 10-30 ms a
    run, so the stretch stands out above the frame loop's own work and the host's noise."""
    rng = np.random.default_rng(1)

    def weight(name: str, shape: tuple[int, ...]) -> onnx.TensorProto:
        return numpy_helper.from_array((rng.standard_normal(shape) * 0.1).astype(np.float32), name)

    return make_model(
        [
            node("Conv", ["image", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
            node("Relu", ["c1"], ["r1"]),
            node("Conv", ["r1", "w2", "b2"], ["c2"], pads=[1, 1, 1, 1]),
            node("Relu", ["c2"], ["r2"]),
            node("GlobalAveragePool", ["r2"], ["g"]),
            node("Flatten", ["g"], ["out"]),
        ],
        [vi("image", list(INPUT_SHAPE), TensorProto.FLOAT)],
        [vi("out", [1, CHANNELS], TensorProto.FLOAT)],
        [
            weight("w1", (CHANNELS, 3, 3, 3)),
            weight("b1", (CHANNELS,)),
            weight("w2", (CHANNELS, CHANNELS, 3, 3)),
            weight("b2", (CHANNELS,)),
        ],
    )


def test_phases_switch_the_slowdown_and_name_each_frame(
    zenoh_router: Router, tmp_path: Path
) -> None:
    model = save(conv_model(), tmp_path / "conv.onnx")
    cfg = fleet_from_dict(
        {
            "fleet": "emulation-it",
            "service": "vision",
            "model": str(model),
            "registry": {"endpoint": zenoh_router.endpoint, "listen": [zenoh_router.endpoint]},
            "machines": {
                "edge-1": {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
                ROBOT: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
            },
            "initial_policy": {"edge-1": "service", ROBOT: "robot"},
            "latency_bound": {"stat": "median", "seconds": 0.3},
            "deadline_s": 0.5,
            "policy": {"kind": "robot"},
        }
    )
    names = ("host speed", "slowed", "host speed again", "slowed again")
    phases = tuple(
        Phase(name, i * FRAMES_PER_PHASE, FRAMES_PER_PHASE, None, SLOWDOWN if i % 2 else 1.0)
        for i, name in enumerate(names)
    )
    telemetry = tmp_path / "robot.jsonl"
    options = RobotOptions(
        source="synthetic",
        frames=len(phases) * FRAMES_PER_PHASE,
        telemetry=telemetry,
        phases=phases,
        registry_wait_s=0.2,  # no registry here: the robot goes on without one
        route_wait_s=0.2,
    )
    daemon = RobotDaemon(cfg, ROBOT, options)
    assert daemon.run() == 0

    lines = [json.loads(line) for line in telemetry.read_text().splitlines()]
    assert [r["frame"] for r in lines] == list(range(len(phases) * FRAMES_PER_PHASE))
    assert [r["phase"] for r in lines] == [n for n in names for _ in range(FRAMES_PER_PHASE)]
    assert {r["action"] for r in lines} == {"P"}
    slowed_phases = {p.name for p in phases if p.slowdown > 1}
    normal = statistics.median(r["latency_s"] for r in lines if r["phase"] not in slowed_phases)
    slowed = statistics.median(r["latency_s"] for r in lines if r["phase"] in slowed_phases)
    assert slowed >= MIN_RATIO * normal, (normal, slowed)


def test_a_bad_slowdown_is_refused_before_anything_starts() -> None:
    with pytest.raises(UserError, match=r"--robot-slowdown 0\.5"):
        RobotOptions(robot_slowdown=0.5).check()
