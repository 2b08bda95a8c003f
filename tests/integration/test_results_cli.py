"""`elasticfog results` as a user runs it: against a fleet whose router is not there, one line
on stderr naming the endpoint and what to start there, and exit code 2 (never a hang); a bad
--count is a usage error."""

from __future__ import annotations

from pathlib import Path

import yaml
from typer.testing import CliRunner

from common.cli import app
from tests.integration.conftest import find_free_port, loopback_endpoint

EXIT_USAGE = 2


def write_fleet(directory: Path, endpoint: str) -> Path:
    path = directory / "fleet.yaml"
    data = {
        "fleet": "results-cli",
        "service": "vision",
        "model": "zoo:vgg",
        "registry": {"endpoint": endpoint},
        "machines": {"edge-1": {"role": "cloud"}, "robot-1": {"role": "robot"}},
        "initial_policy": {"edge-1": "service", "robot-1": "robot"},
        "latency_bound": {"seconds": 0.3},
        "deadline_s": 0.5,
    }
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_an_unreachable_fleet_is_one_line_and_exit_code_2(tmp_path: Path) -> None:
    endpoint = loopback_endpoint(find_free_port())
    config = write_fleet(tmp_path, endpoint)
    result = CliRunner().invoke(app, ["results", "--config", str(config), "--robot", "robot-1"])
    assert result.exit_code == EXIT_USAGE, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and endpoint in lines[0], lines
    # What to start instead, and not zenoh's own "Unable to connect to any of [Single(...)]".
    assert f"cannot reach {endpoint}: nothing answers there; start `elasticfog registry" in lines[0]
    assert "Single(" not in lines[0] and "Unable to connect" not in lines[0], lines


def test_an_unknown_robot_is_named(tmp_path: Path) -> None:
    config = write_fleet(tmp_path, loopback_endpoint(find_free_port()))
    result = CliRunner().invoke(app, ["results", "--config", str(config), "--robot", "robot-9"])
    assert result.exit_code == EXIT_USAGE
    assert "robot-9" in result.output and "robot-1" in result.output
