"""The stereo navigation model on the runtime: zoo:stereo's two image inputs fed from a stereo
source, offloaded at cut 0 as one JPEG per view, with a real registry and cloud daemon.

A registry and a cloud daemon run as subprocesses on loopback (the fleet's model is zoo:stereo
at 160×120, D = 32). The robot renders pairs with `stereo:world`: once through the CLI
(`elasticfog robot --source stereo:world --policy cloud:jpeg80`, its telemetry read back: no
frame lost, each frame's upload a small share of the raw pair), once embedded (`RobotDaemon` with
`on_result`, the way tests see outputs) under `cloud:jpeg80` and `robot`: every frame's d_coll
has the model's bin count, whichever side computed it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.demo import answered_by, read_telemetry
from deploy.local_fleet import LocalFleet
from robotd.daemon import FrameResult, RobotDaemon, RobotOptions
from robotd.telemetry import SERVED_BY_CLOUD, SERVED_BY_ROBOT

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
CLOUD = "edge-1"
STEREO_MODEL = "zoo:stereo"
STEREO_SHAPE = [3, 120, 160]
SOURCE = "stereo:world"
FRAMES = 30
RAW_PAIR_BYTES = 2 * 120 * 160 * 3
MAX_JPEG_SHARE = 0.25
"""Two JPEGs at quality 80 of the rendered views, against the raw pair: about a tenth."""
MIN_ANSWERED_SHARE = 0.8
"""Frames answered by the cloud: the first frames may be finished on the robot while the route
is still on its way (none is lost either way); the rest are answered."""
ROBOT_WAIT_S = 60.0


def _stereo_fleet(make_fleet: Any) -> Any:
    from common.partition import load_partition

    # Split once here so the daemons load the export instead of each making it.
    load_partition(STEREO_MODEL, input_shape=tuple(STEREO_SHAPE))
    return make_fleet(
        model=STEREO_MODEL, input_shape=STEREO_SHAPE, machines={ROBOT: {"source": SOURCE}}
    )


def _bin_count() -> int:
    """The number of curvature bins zoo:stereo says its d_coll has (its metadata)."""
    from nav.zoo_entry import build_stereo

    props = {p.key: p.value for p in build_stereo(tuple(STEREO_SHAPE)).metadata_props}
    return int(props["nav.bins.count"])


def _assert_every_frame_once(records: list[dict[str, Any]], frames: int) -> None:
    assert sorted(int(r["frame"]) for r in records) == list(range(frames)), [
        r["frame"] for r in records
    ]


def _start(lf: LocalFleet) -> None:
    lf.start_registry()
    lf.start_clouds([CLOUD])


def test_cli_robot_offloads_stereo_world_as_two_jpegs_and_loses_no_frame(
    make_fleet: Any, local_fleet: Any, tmp_path: Path
) -> None:
    lf = local_fleet(_stereo_fleet(make_fleet))
    _start(lf)
    telemetry = tmp_path / "robot.jsonl"
    robot = lf.start_robot(
        ROBOT, "--source", SOURCE, "--policy", "cloud:jpeg80", frames=FRAMES, telemetry=telemetry
    )
    assert robot.wait(ROBOT_WAIT_S) == 0, robot.log_tail()
    records = read_telemetry(telemetry)
    _assert_every_frame_once(records, FRAMES)
    answered = [r for r in records if answered_by(r) == CLOUD]
    assert len(answered) >= MIN_ANSWERED_SHARE * FRAMES, [
        (r["frame"], r["reason"]) for r in records if answered_by(r) != CLOUD
    ]
    assert all(r["action"] == "cut:0:jpeg80" for r in records), {r["action"] for r in records}
    per_frame = [int(r["bytes_up"]) for r in answered]
    assert max(per_frame) < MAX_JPEG_SHARE * RAW_PAIR_BYTES, per_frame


@pytest.mark.parametrize(
    ("policy", "served_by"), [("cloud:jpeg80", SERVED_BY_CLOUD), ("robot", SERVED_BY_ROBOT)]
)
def test_embedded_robot_gets_d_coll_with_the_models_bins(
    make_fleet: Any, local_fleet: Any, tmp_path: Path, policy: str, served_by: str
) -> None:
    fleet = _stereo_fleet(make_fleet)
    lf = local_fleet(fleet)
    _start(lf)
    results: list[FrameResult] = []
    options = RobotOptions(
        source=SOURCE, frames=FRAMES, policy=policy, telemetry=tmp_path / "robot.jsonl"
    )
    daemon = RobotDaemon(lf.cfg, ROBOT, options, on_result=results.append)
    assert daemon.run() == 0
    assert [r.frame for r in results] == list(range(FRAMES))
    bins = _bin_count()
    for r in results:
        assert set(r.feeds) == {"left", "right"}
        (d_coll,) = r.outputs.values()
        assert np.asarray(d_coll).shape == (1, bins), (r.frame, np.asarray(d_coll).shape)
        assert np.isfinite(d_coll).all()
    served = [r for r in results if r.served_by == served_by]
    assert len(served) >= MIN_ANSWERED_SHARE * FRAMES, [(r.frame, r.served_by) for r in results]
    _assert_every_frame_once(read_telemetry(tmp_path / "robot.jsonl"), FRAMES)
