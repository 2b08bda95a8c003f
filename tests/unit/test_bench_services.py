"""`bench services` without a testbed: its fleet (three services, the dense model it builds, the
handler it falls back to), its settings' checks, and how a robot's records become the rows of
its JSON contract (phases by start time, deadline misses, lost frames, sums, the goal)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest

from common.config import fleet_from_dict
from common.errors import UserError
from experiments import services as sv
from experiments.dense_model import DENSE_CLASSES, DENSE_OUTPUT, dense_model, write_dense_model
from experiments.fleet import FleetSpec, fleet_dict
from experiments.options import BenchOptions
from experiments.services_rows import (
    CONTENDED,
    INDEPENDENT,
    JOINT,
    MODES,
    PHASES,
    ROW_KEYS,
    UNCONTENDED,
    RunWindows,
    ServiceInfo,
    build_rows,
    goal,
    markdown,
    sum_rows,
)

ADDRESSES = {"registry": "10.77.0.1", "robot": "10.77.0.2", "edge-1": "10.77.0.3"}
SERVICES = (
    ServiceInfo("a", "zoo:mobilenet_v2", "classifier", (3, 120, 160), 2, 0.1, "elastic"),
    ServiceInfo("b", "h:f", "handler", (3, 48, 64), 0, 0.5, "cloud:jpeg90"),
)
UPLINKS = {UNCONTENDED: 20.0, CONTENDED: 2.0}
T0 = 1000.0
CHANGE = T0 + 10.0
STOP = T0 + 22.0


def record(service: str, frame: int, done_at: float, latency_s: float, **extra: Any) -> dict:
    return {
        "service": service,
        "frame": frame,
        "at": done_at,
        "latency_s": latency_s,
        "action": extra.pop("action", "cut:0:jpeg90"),
        "served_by": extra.pop("served_by", "cloud"),
        "prefix_s": 0.001,
        "transfer_s": latency_s / 2,
        "cloud_s": latency_s / 2,
        "suffix_local_s": 0.0,
        "robot_cpu_s": 0.002,
        "bytes_up": 4000,
        **extra,
    }


def one_run(mode: str, contended_latency_s: float, *, skip: int | None = None) -> RunWindows:
    """Each service: a frame every second from T0 - 2 (warm-up) to STOP + 1 (after the end),
    0.05 s before the change and `contended_latency_s` after it; frame `skip` never reported."""
    records = []
    for service in SERVICES:
        for frame, start in enumerate(np.arange(T0 - 2, STOP + 2, 1.0)):
            if frame == skip:
                continue
            latency = 0.05 if start < CHANGE else contended_latency_s
            records.append(record(service.name, frame, float(start) + latency, latency))
    windows = {UNCONTENDED: (T0, CHANGE), CONTENDED: (CHANGE + 2.0, STOP)}
    return RunWindows(mode, 1, records, windows)


def test_frames_fall_in_the_phase_they_started_in_and_lost_ones_are_counted() -> None:
    run = one_run(JOINT, 0.3, skip=5)
    # Started at T0 .. T0 + 9 (frame 5 missing), and at CHANGE + 2 .. STOP - 1.
    assert len(run.in_phase("a", UNCONTENDED)) == 9
    assert len(run.in_phase("a", CONTENDED)) == 10
    assert run.lost("a") == {UNCONTENDED: 1, CONTENDED: 0}
    assert one_run(JOINT, 0.3).lost("b") == {UNCONTENDED: 0, CONTENDED: 0}


def test_rows_keep_the_contract_for_every_mode_phase_and_service() -> None:
    runs = [one_run(JOINT, 0.3), one_run(INDEPENDENT, 0.6, skip=15)]
    rows = build_rows(runs, SERVICES, UPLINKS)
    assert {(r.mode, r.phase, r.service) for r in rows} == {
        (m, p, s.name) for m in MODES for p in PHASES for s in SERVICES
    }
    for row in rows:
        data = row.to_json()
        assert list(data)[: len(ROW_KEYS)] == list(ROW_KEYS)
        assert data["uplink_mbit"] == UPLINKS[row.phase]
    (a_joint,) = [r for r in rows if (r.mode, r.phase, r.service) == (JOINT, CONTENDED, "a")]
    assert a_joint.frames == 10 and a_joint.lost == 0
    assert a_joint.mean_latency_s == pytest.approx(0.3)
    assert a_joint.deadline_misses == 10  # 0.3 s against a 0.1 s deadline
    (b_joint,) = [r for r in rows if (r.mode, r.phase, r.service) == (JOINT, CONTENDED, "b")]
    assert b_joint.deadline_misses == 0  # 0.3 s against 0.5 s
    (a_indep,) = [r for r in rows if (r.mode, r.phase, r.service) == (INDEPENDENT, CONTENDED, "a")]
    assert a_indep.lost == 1 and a_indep.frames == 9


def test_sums_and_the_goal() -> None:
    runs = [one_run(JOINT, 0.3), one_run(INDEPENDENT, 0.6)]
    rows = build_rows(runs, SERVICES, UPLINKS)
    sums = sum_rows(rows)
    assert {(s.mode, s.phase) for s in sums} == {(m, p) for m in MODES for p in PHASES}
    (joint,) = [s for s in sums if (s.mode, s.phase) == (JOINT, CONTENDED)]
    assert joint.p95_latency_s == pytest.approx(0.6)
    assert joint.frames == 20
    result = goal(sums)
    assert result.contended_ratio == pytest.approx(2.0)
    assert result.uncontended_ratio == pytest.approx(1.0)
    assert result.met is True
    assert goal(sum_rows(build_rows([one_run(JOINT, 0.3)], SERVICES, UPLINKS))).met is None


def test_markdown_shows_both_phases_the_sums_the_goal_and_where_the_time_goes() -> None:
    runs = [one_run(JOINT, 0.3), one_run(INDEPENDENT, 0.6)]
    rows = build_rows(runs, SERVICES, UPLINKS)
    sums = sum_rows(rows)
    text = markdown(rows, sums, goal(sums), UPLINKS)
    assert "**uncontended uplink (20 Mbit/s)**" in text
    assert "**contended uplink (2 Mbit/s)**" in text
    assert "| **sum** |" in text
    assert "2.00x" in text and "(met)" in text
    assert "where the time goes" in text


def test_the_dense_model_answers_per_pixel(tmp_path: Path) -> None:
    model = dense_model((3, 48, 64))
    onnx.checker.check_model(model, full_check=True)
    import onnxruntime as ort

    path = write_dense_model(tmp_path, (3, 48, 64))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (scores,) = session.run(None, {"input": np.zeros((1, 48, 64, 3), np.uint8)})
    assert session.get_outputs()[0].name == DENSE_OUTPUT
    assert scores.shape == (1, DENSE_CLASSES, 48, 64) and scores.dtype == np.float32
    with pytest.raises(ValueError, match="multiples of 4"):
        dense_model((3, 50, 64))


def test_the_fleet_has_three_ranked_services_and_loads(tmp_path: Path) -> None:
    infos, mapping = sv.services(tmp_path)
    assert [i.kind for i in infos] == ["classifier", "dense", "handler"]
    assert len({i.priority for i in infos}) == 3
    assert mapping[sv.HANDLER]["policy"] == {"kind": sv.HANDLER_POLICY}
    spec = FleetSpec(fleet="s1", services=mapping, deadline_s=1.0, fps=5.0)
    data = fleet_dict(spec, ADDRESSES, tmp_path / "rib.sqlite")
    assert "service" not in data and "model" not in data and "input_shape" not in data
    cfg = fleet_from_dict(data, source=tmp_path / "s1.yaml")
    assert list(cfg.services) == [sv.CLASSIFIER, sv.DENSE, sv.HANDLER]
    assert cfg.services_of("robot-1") == list(cfg.services)
    assert cfg.for_service(sv.CLASSIFIER).deadline_s == infos[0].deadline_s


def test_without_the_apriltag_handler_the_bench_writes_its_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sv, "APRILTAG_HANDLER", "no_such_package.tags:detect")
    handler, params = sv.handler_spec(tmp_path)
    assert handler == sv.OWN_HANDLER and params == {}
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module(sv.OWN_HANDLER_MODULE)
    try:
        image = np.zeros((1, 48, 64, 3), np.uint8)
        image[0, 10:30, 10:40] = 255
        out = module.detect({"image": image})
        assert set(out) == {"boxes", "centres"} and len(out["boxes"]) >= 1
    finally:
        sys.modules.pop(sv.OWN_HANDLER_MODULE, None)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"fps": 0.0}, "--fps 0: must be a positive number"),
        ({"contended_mbit": 30.0}, "--contended-mbit 30: must be positive and below"),
        ({"rounds": 0}, "--rounds 0: expected at least 1"),
        ({"phase_s": 1.0}, "--phase-s 1: expected at least 2"),
        ({"handler_policy": "nope"}, "--handler-policy: unknown policy 'nope'"),
    ],
)
def test_bad_settings_are_one_line(changes: dict[str, Any], message: str) -> None:
    with pytest.raises(UserError, match=message.replace("(", r"\(")):
        sv.plan(BenchOptions(), **changes)


def test_quick_is_one_short_round_and_the_frames_are_only_a_bound() -> None:
    quick = sv.plan(BenchOptions(quick=True))
    full = sv.plan(BenchOptions())
    assert (quick.rounds, full.rounds) == (sv.QUICK_ROUNDS, sv.FULL_ROUNDS)
    assert quick.phase_s < full.phase_s
    assert quick.frames_cap > quick.fps * (2 * quick.phase_s + quick.settle_s)
