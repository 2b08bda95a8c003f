"""The bench's h264 rows without a testbed (docs/video.md, "Table I with h264"): the
`elastic-h264` variant is elastic with `fidelity.video` on in the robot's copy of the fleet file
only (`elastic-h264only`: with h264 its only lossy codec), `cloud:h264` and the variants are
policy names the bench takes, and `--source` reaches the robot's machine entry (a generated
camera only)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from common.config import load_fleet
from common.defaults import DEFAULT_CAMERA_SOURCE
from common.errors import UserError
from experiments.fleet import (
    POLICY_VARIANTS,
    ROBOT_ID,
    FleetSpec,
    PolicyVariant,
    fleet_dict,
    write_fleet,
    write_robot_variant,
)
from experiments.glitch import GlitchSettings
from experiments.options import BenchOptions, parse_names
from experiments.table1 import Table1Settings
from robotd.policies import check_policy, policy_names

ROOT = Path(__file__).resolve().parents[2]
ADDRESSES = {"registry": "10.77.0.1", "robot": "10.77.0.2", "edge-1": "10.77.0.3"}
PAN = "photo:astronaut,motion=pan"


def test_elastic_h264_is_elastic_with_video_in_the_robots_copy_only(tmp_path: Path) -> None:
    assert POLICY_VARIANTS["elastic-h264"] == PolicyVariant(
        "elastic", fleet={"fidelity": {"video": True}}
    )
    path, cfg = write_fleet(FleetSpec(fleet="h1"), ADDRESSES, tmp_path)
    assert cfg.fidelity.video is False
    variant, kind = write_robot_variant(path, "elastic-h264")
    assert kind == "elastic"
    data = yaml.safe_load(variant.read_text())
    assert data["policy"] == {"kind": "elastic", "params": {}}
    assert data["fidelity"] == {"video": True}
    loaded = load_fleet(variant)
    assert loaded.fleet == "h1" and loaded.fidelity.video is True
    assert load_fleet(path).fidelity.video is False  # the deployments' file is unchanged
    # A variant's fleet changes merge into what the fleet file has, and stay the variant's.
    data = yaml.safe_load(path.read_text())
    data["fidelity"] = {"min_top1_agreement": 0.9}
    path.write_text(yaml.safe_dump(data))
    merged = yaml.safe_load(write_robot_variant(path, "elastic-h264")[0].read_text())
    assert merged["fidelity"] == {"min_top1_agreement": 0.9, "video": True}
    assert POLICY_VARIANTS["elastic-h264"].fleet == {"fidelity": {"video": True}}
    nohedge = yaml.safe_load(write_robot_variant(path, "elastic-nohedge")[0].read_text())
    assert "video" not in nohedge["fidelity"]
    only = load_fleet(write_robot_variant(path, "elastic-h264only")[0])
    assert only.fidelity.video is True and only.fidelity.codecs == ["h264"]


def test_the_h264_policies_parse_as_bench_policies() -> None:
    names = "robot,cloud:jpeg50,cloud:h264,elastic,elastic-h264,elastic-h264only"
    known = list(policy_names(real_time=True))
    assert parse_names(names, "--policies", known) == names.split(",")
    check_policy("cloud:h264", real_time=True)
    with pytest.raises(UserError, match="unknown elastic-h265"):
        parse_names("elastic-h265", "--policies", known)


def test_the_source_reaches_the_robot_and_must_be_generated(tmp_path: Path) -> None:
    robot = fleet_dict(FleetSpec(fleet="s"), ADDRESSES, tmp_path / "db")["machines"][ROBOT_ID]
    assert robot["source"] == DEFAULT_CAMERA_SOURCE
    _, cfg = write_fleet(FleetSpec(fleet="s2", source=PAN), ADDRESSES, tmp_path)
    assert cfg.machines[ROBOT_ID].source == PAN
    BenchOptions(source=PAN).check()
    BenchOptions(source="synthetic:every=4").check()
    with pytest.raises(UserError, match="--source 'zenoh'"):
        BenchOptions(source="zenoh").check()
    with pytest.raises(UserError, match=r"--source: .*unknown photo 'nope'"):
        BenchOptions(source="photo:nope").check()
    # The JSON's settings say which camera the run had.
    assert Table1Settings("zoo:vgg", [3, 480, 640], 0.5, 60, 10).to_json()["source"] == "photo"
    glitch = GlitchSettings("zoo:vgg", [3, 480, 640], 0.5, 10, 20, 50, source=PAN)
    assert glitch.to_json()["source"] == PAN


def test_table1_refuses_a_bad_source_before_it_starts(tmp_path: Path) -> None:
    command = ["bench", "table1", "--source", "camera:0", "--quick"]
    done = subprocess.run(
        [sys.executable, "-c", "from common.cli import main; main()", *command],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"},
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "--source 'camera:0'" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
