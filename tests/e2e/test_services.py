"""Several services per robot, end to end: a fleet file written from the `services:` contract
alone, with a zoo model, an ONNX model written here (not by the project's zoo) and a Python
handler written here, next to the fleet file; the registry, two cloud daemons and one robot as
real subprocesses on loopback.

edge-1 serves all three services and starts in service; edge-2 serves two of them. The robot
uses all three from one capture. Every service is answered by edge-1 for at least 90% of its
frames; `routes --json` has a row per (robot, service); `results --json --service NAME` lines
carry that service. Killing edge-1 moves the two services edge-2 also serves to it and leaves
the third to the robot, and no frame of any service is lost.
"""

from __future__ import annotations

import json
import subprocess
import textwrap
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from deploy.demo import read_telemetry
from deploy.local_fleet import LocalFleet
from deploy.procs import elasticfog_argv
from deploy.readiness import wait_until
from tests.e2e.conftest import TEST_MODEL, Fleet

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
SHARED = ("detect", "tags")  # edge-1 and edge-2
ONLY_EDGE1 = "segment"
SERVICES = ("detect", "segment", "tags")
FRAMES = 240
FPS = 12.0
WAIT_S = 60.0
ANSWERED_SHARE = 0.9
BEFORE_KILL = 20  # cloud answers per service before edge-1 is killed

HANDLER = '''
"""A user's handler: the image's mean colour and a 4x4 grid of its brightness."""
import cv2
import numpy as np


def colour(inputs, grid=4):
    image = inputs["image"][0]
    small = cv2.resize(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), (grid, grid),
                       interpolation=cv2.INTER_AREA)
    return {
        "mean_rgb": image.reshape(-1, 3).mean(axis=0).astype(np.float32),
        "grid": small.astype(np.float32) / 255.0,
    }
'''


def _dense_model(path: Path, height: int, width: int) -> None:
    """A small dense-output ONNX model of the camera image (uint8 1xHxWx3): normalize, two
    3x3 convolutions, a per-pixel score map. Weights seeded here."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(7)
    w1 = numpy_helper.from_array(rng.normal(0, 0.2, (8, 3, 3, 3)).astype(np.float32), "w1")
    w2 = numpy_helper.from_array(rng.normal(0, 0.2, (2, 8, 3, 3)).astype(np.float32), "w2")
    scale = numpy_helper.from_array(np.array(1 / 255.0, dtype=np.float32), "scale")
    nodes = [
        helper.make_node("Cast", ["image"], ["f"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["f", "scale"], ["fs"]),
        helper.make_node("Transpose", ["fs"], ["x"], perm=[0, 3, 1, 2]),
        helper.make_node("Conv", ["x", "w1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("Conv", ["r1", "w2"], ["scores"], pads=[1, 1, 1, 1]),
    ]
    graph = helper.make_graph(
        nodes,
        "dense",
        [helper.make_tensor_value_info("image", TensorProto.UINT8, [1, height, width, 3])],
        [helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, 2, height, width])],
        initializer=[w1, w2, scale],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _services_fleet(base: Fleet) -> Path:
    """The test fleet turned into a three-service one (the one-service keys removed)."""
    data: dict[str, Any] = yaml.safe_load(base.config.read_text())
    data.pop("service")
    data.pop("model")
    _, h, w = data["input_shape"]
    (base.dir / "usercolour.py").write_text(textwrap.dedent(HANDLER))
    _dense_model(base.dir / "dense.onnx", h, w)
    data["services"] = {
        "detect": {"model": TEST_MODEL},
        # A file's input_shape is the whole tensor's (the fleet's is a zoo model's C, H, W).
        "segment": {"model": "dense.onnx", "input_shape": [1, h, w, 3], "priority": 2},
        "tags": {"handler": "usercolour:colour", "params": {"grid": 4}},
    }
    machines = data["machines"]
    machines["edge-1"]["services"] = list(SERVICES)
    machines["edge-2"]["services"] = list(SHARED)
    machines[ROBOT]["fps"] = FPS
    data["initial_policy"] = {"edge-1": "service"}
    base.config.write_text(yaml.safe_dump(data, sort_keys=False))
    return base.config


def _records(path: Path) -> list[dict[str, Any]]:
    return read_telemetry(path) if path.exists() else []


def _cloud_answers(records: list[dict[str, Any]], service: str, deployment: str) -> int:
    return sum(
        1
        for r in records
        if r.get("service") == service
        and r["served_by"] == "cloud"
        and r["deployment"] == deployment
    )


def _cli(lf: LocalFleet, *args: str) -> str:
    done = subprocess.run(
        [*elasticfog_argv(), *args, "--config", str(lf.config)],
        capture_output=True,
        text=True,
        timeout=WAIT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_three_services_route_fail_over_and_lose_nothing(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    config = _services_fleet(make_fleet())
    lf: LocalFleet = local_fleet(Fleet(tmp_path, config, "", {}))
    telemetry = tmp_path / "robot.jsonl"
    lf.start_registry()
    lf.start_clouds()
    robot = lf.start_robot(
        ROBOT, "--policy", "cloud", frames=FRAMES, telemetry=telemetry, wait=True
    )

    def answered_everywhere() -> bool:
        records = _records(telemetry)
        return all(_cloud_answers(records, s, "edge-1") >= BEFORE_KILL for s in SERVICES)

    wait_until(answered_everywhere, timeout_s=WAIT_S, what="answers by edge-1", procs=[robot])

    rows = json.loads(_cli(lf, "routes", "--json"))
    routes = {(r["robot"], r["service"]): r["deployment"] for r in rows}
    assert routes == {(ROBOT, s): "edge-1" for s in SERVICES}, rows

    out = subprocess.run(
        [
            *elasticfog_argv(), "results", "--config", str(config),
            "--robot", ROBOT, "--service", "tags", "--count", "3", "--json", "--timeout", "20",
        ],
        capture_output=True, text=True, timeout=WAIT_S, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(lines) == 3 and {line["service"] for line in lines} == {"tags"}, lines
    assert set(lines[0]["outputs"]) == {"mean_rgb", "grid"}

    before = _records(telemetry)
    for service in SERVICES:
        mine = [r for r in before if r["service"] == service]
        share = _cloud_answers(before, service, "edge-1") / len(mine)
        assert share >= ANSWERED_SHARE, (service, share, Counter(r["reason"] for r in mine))

    lf.kill("edge-1")

    def moved() -> bool:
        records = _records(telemetry)
        return all(_cloud_answers(records, s, "edge-2") >= 5 for s in SHARED)

    wait_until(moved, timeout_s=WAIT_S, what="detect and tags answered by edge-2", procs=[robot])
    rows = json.loads(_cli(lf, "routes", "--json"))
    routes = {r["service"]: r["deployment"] for r in rows if r["robot"] == ROBOT}
    assert routes == {"detect": "edge-2", "tags": "edge-2", ONLY_EDGE1: None}, rows

    robot.wait(WAIT_S * 2)
    records = _records(telemetry)
    for service in SERVICES:
        frames = sorted(r["frame"] for r in records if r["service"] == service)
        assert frames == list(range(FRAMES)), f"{service}: frames lost or doubled"
    after = [r for r in records if r["service"] == ONLY_EDGE1 and r["deployment"] != "edge-1"]
    assert after and all(r["served_by"] == "robot" for r in after)
