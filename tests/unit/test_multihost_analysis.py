"""The multi-host experiments' plumbing without a testbed: the fleet file they write and the way
telemetry is cut into before / on / after (runs anywhere, no root, no daemons)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from common.config import load_fleet
from common.session import zenoh_settings
from experiments.fleet import FleetSpec, fleet_dict, write_fleet, write_robot_variant
from experiments.stats import lost_frames, phases, settle_frames, summary

ADDRESSES = {
    "registry": "10.77.0.1",
    "robot": "10.77.0.2",
    "edge-1": "10.77.0.3",
    "edge-2": "10.77.0.4",
    "bench": "10.77.0.5",
}


def _rec(frame: int, action: str, latency_s: float = 0.1) -> dict[str, Any]:
    return {
        "frame": frame,
        "action": action,
        "latency_s": latency_s,
        "robot_cpu_s": 0.01,
        "energy_j": 0.5,
        "bytes_up": 0 if action == "P" else 1000,
        "deployment": None if action == "P" else "edge-1",
        "fallback": False,
    }


def test_fleet_endpoints_are_testbed_addresses_with_shared_memory_off(tmp_path: Path) -> None:
    spec = FleetSpec(fleet="t1", clouds=("edge-1", "edge-2"), serving="edge-2", fps=5.0)
    path, cfg = write_fleet(spec, ADDRESSES, tmp_path)
    assert load_fleet(path).fleet == "t1"
    assert cfg.registry.endpoint == "tcp/10.77.0.1:7447"
    assert cfg.registry.listen == ["tcp/10.77.0.1:7447"]
    assert cfg.machines["edge-1"].listen == ["tcp/10.77.0.3:7448"]
    assert cfg.machines["robot-1"].listen == ["tcp/10.77.0.2:7448"]
    assert cfg.initial_service("robot-1") == "edge-2"
    assert cfg.zenoh.shared_memory is False
    robot = zenoh_settings(cfg, machine="robot-1")
    assert robot["scouting/multicast/enabled"] is False
    assert robot["transport/shared_memory/enabled"] is False
    assert robot["connect/endpoints"] == ["tcp/10.77.0.1:7447"]


def test_fleet_refuses_a_host_the_testbed_lacks() -> None:
    with pytest.raises(ValueError, match="no host cloud-1"):
        fleet_dict(FleetSpec(fleet="x", clouds=("cloud-1",), serving="cloud-1"), ADDRESSES, Path())


def test_policy_variant_is_a_robot_config_of_the_same_fleet(tmp_path: Path) -> None:
    path, _ = write_fleet(FleetSpec(fleet="v1"), ADDRESSES, tmp_path)
    variant, kind = write_robot_variant(path, "elastic-nohedge")
    assert kind == "elastic"
    data = yaml.safe_load(variant.read_text())
    assert data["policy"] == {"kind": "elastic", "params": {"hedge": False}}
    assert load_fleet(variant).fleet == "v1"
    assert write_robot_variant(path, "cloud") == (path, "cloud")


def test_settle_counts_frames_until_the_final_action_holds() -> None:
    # Frames 0-9 offload, the change is at 10, the policy wanders 3 frames then stays on P.
    records = [_rec(f, "cut:0") for f in range(10)]
    records += [_rec(10, "cut:0"), _rec(11, "cut:9"), _rec(12, "cut:0")]
    records += [_rec(f, "P") for f in range(13, 40)]
    assert settle_frames(records, 10) == 3
    ph = phases(records, 0, 10)
    assert ph.settle_frames == 3
    assert ph.before.frames == 10 and ph.before.main_action == "cut:0"
    assert ph.on.frames == 3
    assert ph.after.main_action == "P" and ph.after.frames == 27


def test_a_policy_that_never_changes_settles_at_once_but_on_lasts_three_frames() -> None:
    records = [_rec(f, "cut:0", 0.1 if f < 10 else 1.0) for f in range(30)]
    ph = phases(records, 0, 10)
    assert ph.settle_frames == 0
    assert ph.on.frames == 3
    assert ph.before.mean_latency_s == pytest.approx(0.1)
    assert ph.after.mean_latency_s == pytest.approx(1.0)


def test_exploration_frames_do_not_undo_settling() -> None:
    # After the change: P with a forced cut:9 every fifth frame (80% of any 10 frames are P).
    records = [_rec(f, "cut:0") for f in range(10)]
    records += [_rec(f, "cut:9" if f % 5 == 0 else "P") for f in range(10, 50)]
    assert settle_frames(records, 10) == 1  # frame 10 explores; P holds from frame 11


def test_lost_frames_and_summary() -> None:
    records = [_rec(f, "P", 0.2) for f in (0, 1, 3)]
    assert lost_frames(records, 5) == [2, 4]
    s = summary(records)
    assert s.frames == 3 and s.fallbacks == 0
    assert s.mean_latency_s == pytest.approx(0.2) and s.bytes_up == 0
