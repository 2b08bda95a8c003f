"""The codecs of a robot whose frames arrive on their own (`zenoh`, `ros2:`), measured on the first
frames it serves (`robotd.robot_profile.FirstFramesRefinement`, `robotd.calibration`).

Regression guard (issue 33): such a robot measured its codecs at start on scikit-image's
photographs, which the runtime lock a robot installs does not have. What must hold now: until its
frames are measured it starts from defaults that admit no lossy action it was not asked for (raw
at every cut, and the codecs its policy names); the measurement on its own frames goes through
the fidelity gate and is cached; a robot stopping meanwhile gives the measurement up and caches
nothing.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.codec_profile import Fidelity
from common.partition import load_partition
from common.partition.runtime import SplitModel
from robotd.calibration import CodecCalibration
from robotd.policies import FrameContext, Objective, Policy, make_policy
from robotd.robot_profile import FirstFramesRefinement, robot_profile
from tests.helpers.onnx_graphs import camera_classifier, save

FRAMES = 3


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> SplitModel:
    path = save(camera_classifier(), tmp_path_factory.mktemp("model") / "camera.onnx")
    return SplitModel(load_partition(str(path)))


def frames(count: int) -> list[dict[str, np.ndarray]]:
    """Smooth frames (gradients and a moving square) as a camera's: not noise."""
    out = []
    y, x = np.mgrid[0:16, 0:16]
    for n in range(count):
        image = np.stack([x * 12 + n, y * 12, (x + y) * 6], axis=-1).astype(np.uint8)
        image[4 + n : 9 + n, 5:10] = 220
        out.append({"image": image[None]})
    return out


def calibration(model: SplitModel, tmp_path: Path, **key: Any) -> CodecCalibration:
    return CodecCalibration(
        model, Fidelity(), {0: ["jpeg80"]}, {"source": "zenoh", "test": str(tmp_path), **key}
    )


def test_defaults_are_raw_and_the_named_codecs_only(model: SplitModel, tmp_path: Path) -> None:
    table = calibration(model, tmp_path).defaults()
    assert sorted(table) == [cut.index for cut in model.partition.cuts]
    first, *others = sorted(table)
    assert [e["name"] for e in table[first]] == ["raw", "jpeg80"]  # named by the policy
    assert all([e["name"] for e in table[k]] == ["raw"] for k in others)  # jpeg80 cannot apply
    assert all(e["action"] and not e["measured"] for entries in table.values() for e in entries)
    profile = robot_profile(model, frames(1)[0], runs=1, codecs=table)
    # The baseline that names it is built on the defaults and sends it from the first frame.
    decision = make_policy("cloud:jpeg80", profile).decide(FrameContext(index=0))
    assert (decision.action, decision.codec) == (first, "jpeg80")


def build(profile: dict[str, Any]) -> Policy:
    return make_policy("elastic", profile, None, Objective.parse(None))


def test_the_first_frames_are_measured_through_the_gate_and_cached(
    model: SplitModel, tmp_path: Path
) -> None:
    calib = calibration(model, tmp_path)
    start = robot_profile(model, frames(1)[0], runs=1, codecs=calib.defaults())
    refinement = FirstFramesRefinement(calib, start, build, count=FRAMES)
    offered = [refinement.offer(f) for f in frames(FRAMES + 1)]
    assert offered == [False] * (FRAMES - 1) + [True, True]
    assert len(refinement.frames) == FRAMES  # a frame past the count is not kept
    policy = refinement.refined()
    assert policy is not None
    table = calib.cached()
    assert table is not None, "the measurement is cached: the next start reads it"
    lowest = min(table)
    measured = {e["name"]: e for e in table[lowest]}
    # Every candidate of the camera image was measured, lossy ones against the whole model.
    assert {"png", "jpeg95", "jpeg50", "jpeg80"} <= set(measured)
    assert all(measured[n]["top1_agreement"] is not None for n in ("jpeg95", "jpeg50"))
    actions = {(k, e["name"]) for k, entries in table.items() for e in entries if e["action"]}
    assert set(zip(policy.cuts.indices, policy.cuts.codecs, strict=True)) <= actions
    fidelity = Fidelity()
    for k, name in actions:
        entry = next(e for e in table[k] if e["name"] == name)
        if entry["lossy"] and name != "jpeg80":  # jpeg80: named by the policy, kept whatever
            assert fidelity.admits(entry["top1_agreement"], entry["rel_err"])


def test_a_robot_stopping_gives_the_measurement_up(model: SplitModel, tmp_path: Path) -> None:
    calib = calibration(model, tmp_path, stopped=True)
    start = robot_profile(model, frames(1)[0], runs=1, codecs=calib.defaults())
    refinement = FirstFramesRefinement(calib, start, build, count=FRAMES)
    for f in frames(FRAMES):
        refinement.offer(f)
    stop = threading.Event()
    stop.set()
    assert refinement.refined(stop) is None
    assert calib.cached() is None
