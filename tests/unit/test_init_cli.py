"""`elasticfog init DIR`: a commented single-host fleet.yaml that loads, and no silent overwrite."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from common.cli import app
from common.config import load_fleet
from common.init_cli import render_fleet
from common.source_spec import KINDS, parse_source
from common.wire.registry import DeploymentState

runner = CliRunner()


def invoke(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, ["init", *args])
    return result.exit_code, result.output


def test_writes_a_commented_single_host_fleet_that_loads(tmp_path: Path) -> None:
    code, output = invoke(str(tmp_path / "fleet"))
    target = tmp_path / "fleet" / "fleet.yaml"
    assert code == 0, output
    assert str(target) in output
    text = target.read_text()
    assert sum(line.lstrip().startswith("#") for line in text.splitlines()) >= 10
    config = load_fleet(target)
    assert config.fleet == "default"
    assert config.registry.endpoint == "tcp/127.0.0.1:7447"
    assert config.registry.listen == ["tcp/127.0.0.1:7447"]
    assert config.deployment_ids == ["edge-1", "edge-2"]
    assert config.robot_ids == ["robot-1"]
    assert config.initial_state("edge-1", "robot-1") is DeploymentState.SERVICE
    assert config.initial_state("edge-2", "robot-1") is DeploymentState.STANDBY
    assert config.model == "zoo:resnet"
    assert config.latency_bound.seconds > 0
    assert config.deadline_s > 0
    # Single host: every machine listens on loopback only.
    for machine_id in config.machines:
        assert all("127.0.0.1" in e for e in config.machine(machine_id).listen)


def test_the_robot_source_comment_names_every_source_kind() -> None:
    """Guards against the comment naming only video and camera (a user never learnt of zenoh,
    ros2 or bag from the file init wrote)."""
    lines = render_fleet().splitlines()
    at = next(i for i, line in enumerate(lines) if line.strip().startswith("source:"))
    comment = []
    for line in reversed(lines[:at]):
        if not line.strip().startswith("#"):
            break
        comment.append(line)
    text = " ".join(comment)
    for kind in KINDS:
        assert kind in text, kind
    assert parse_source("camera:/dev/video0").index == 0  # the form the comment shows


def test_options_end_up_in_the_file(tmp_path: Path) -> None:
    model = tmp_path / "net.onnx"
    model.write_bytes(b"not checked here")
    code, output = invoke(str(tmp_path), "--port", "7600", "--fleet", "yes", "--model", str(model))
    assert code == 0, output
    config = load_fleet(tmp_path / "fleet.yaml")
    assert config.registry.endpoint == "tcp/127.0.0.1:7600"
    assert config.fleet == "yes"  # quoted in the file: YAML would read a bare yes as true
    assert config.model_path == model.resolve()
    code, output = invoke(str(tmp_path / "b"), "--model", "zoo:resnet")
    assert code == 0, output
    assert load_fleet(tmp_path / "b" / "fleet.yaml").zoo_model == "resnet"


def test_refuses_to_overwrite_without_force(tmp_path: Path) -> None:
    assert invoke(str(tmp_path))[0] == 0
    target = tmp_path / "fleet.yaml"
    target.write_text("# edited by hand\n")
    code, output = invoke(str(tmp_path), "--port", "7700")
    assert code == 2
    assert "already exists" in output and "--force" in output
    assert target.read_text() == "# edited by hand\n"
    code, output = invoke(str(tmp_path), "--port", "7700", "--force")
    assert code == 0, output
    assert load_fleet(target).registry.endpoint == "tcp/127.0.0.1:7700"


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--fleet", "a/b"], "fleet name 'a/b' contains '/'"),
        (["--fleet", ""], "fleet name must not be empty"),
        (["--port", "0"], "--port 0"),
        (["--port", "70000"], "--port 70000"),
        (["--model", "missing.onnx"], "--model missing.onnx: no such file"),
        (["--model", "zoo:"], "zoo model name must not be empty"),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path: Path, args: list[str], words: str) -> None:
    code, output = invoke(str(tmp_path / "out"), *args)
    assert code == 2
    assert words in output
    assert len(output.strip().splitlines()) == 1
    assert "Traceback" not in output
    assert not (tmp_path / "out").exists()


def test_dir_that_is_a_file(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, output = invoke(str(blocker))
    assert code == 2 and "not a directory" in output
