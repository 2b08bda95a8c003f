"""One strict YAML reader for every file a user writes: a key given twice in a fleet file, a demo
script, a robot's phases or a simulator trace is refused in one line naming the file, the key and
both lines, by the loader and through the CLI (exit code 2, one line on stderr). Guards against
PyYAML's default, which keeps the last of two equal keys silently (a phase's `uplink_mbit` written
twice ran with the second, and nobody was told). Also: the one ValidationError wording."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from typer.testing import CliRunner

from common.cli import app
from common.config import load_fleet
from common.errors import UserError
from common.init_cli import write_fleet
from common.yaml_files import format_validation_error, read_yaml
from deploy.demo_script import load_script
from robotd.emulation import load_phases
from robotd.sim.trace import load_trace

EXIT_USAGE = 2
PROFILE = Path(__file__).resolve().parents[1] / "data" / "profiles" / "vgg-like-3x240x320.json"

# Each file has `uplink_mbit` on line 3 and again on line 4 (where the second one starts: column 5).
SCRIPT = """\
phases:
  - name: good link
    uplink_mbit: 8
    uplink_mbit: 0.2
    frames: 10
"""
TRACE = """\
frames_per_second: 10
segments:
  - {frames: 10, uplink_mbit: 10, downlink_mbit: 50, rtt_ms: 10, robot_cpu: 1, cloud_speedup: 8,
    uplink_mbit: 1}
"""
DUPLICATE = "line 4, column 5: duplicate key 'uplink_mbit', first given on line 3"


def _write(tmp_path: Path, text: str, name: str = "file.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _refusal(load: Callable[[Path], Any], path: Path) -> str:
    with pytest.raises(UserError) as caught:
        load(path)
    message = str(caught.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize(
    ("load", "text", "head"),
    [
        (load_script, SCRIPT, "--script"),
        (load_phases, SCRIPT, "--phases"),
        (load_trace, TRACE, "trace"),
    ],
    ids=["demo script", "phases", "trace"],
)
def test_a_key_given_twice_is_refused_naming_file_key_and_both_lines(
    tmp_path: Path, load: Callable[[Path], Any], text: str, head: str
) -> None:
    path = _write(tmp_path, text)
    message = _refusal(load, path)
    assert message == f"{head} {path}: invalid YAML: {DUPLICATE}"


def test_a_fleet_file_with_a_key_given_twice_names_both_lines(tmp_path: Path) -> None:
    fleet = write_fleet(tmp_path)
    text = fleet.read_text(encoding="utf-8").replace(
        "deadline_s: 0.5\n", "deadline_s: 0.5\ndeadline_s: 5\n"
    )
    fleet.write_text(text, encoding="utf-8")
    first = text.splitlines().index("deadline_s: 0.5") + 1
    message = _refusal(load_fleet, fleet)
    assert message.startswith(f"{fleet}: invalid YAML: line {first + 1}, column 1: ")
    assert message.endswith(f"duplicate key 'deadline_s', first given on line {first}")


def test_equal_keys_in_different_mappings_are_no_duplicates(tmp_path: Path) -> None:
    path = _write(tmp_path, "a: {x: 1}\nb: {x: 2}\nc: [{x: 1}, {x: 1}]\n")
    assert read_yaml(path) == {"a": {"x": 1}, "b": {"x": 2}, "c": [{"x": 1}, {"x": 1}]}


def test_the_robots_phases_written_by_the_demo_read_back_strictly(tmp_path: Path) -> None:
    """What the demo hands the robot (`--phases`) is read by the same strict reader."""
    script = load_script(_write(tmp_path, SCRIPT.replace("    uplink_mbit: 0.2\n", "")))
    phases = _write(tmp_path, script.robot_phases_yaml(), "phases.yaml")
    assert list(load_phases(phases)) == list(script.phases)


# -- through the CLI -------------------------------------------------------------------------------
def _cli(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(app, list(args))
    return result.exit_code, result.stdout, result.stderr


def _assert_one_line(code: int, out: str, err: str, *fragments: str) -> None:
    assert code == EXIT_USAGE, (out, err)
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert "Traceback" not in out + err


def test_demo_refuses_a_script_with_a_key_given_twice(tmp_path: Path) -> None:
    path = _write(tmp_path, SCRIPT, "script.yaml")
    # Refused before anything starts: no daemon, no port, no model.
    _assert_one_line(*_cli("demo", "--script", str(path)), f"--script {path}", DUPLICATE)


def test_robot_refuses_phases_with_a_key_given_twice(tmp_path: Path) -> None:
    fleet = write_fleet(tmp_path / "fleet")
    phases = _write(tmp_path, SCRIPT, "phases.yaml")
    args = ("robot", "--config", str(fleet), "--id", "robot-1", "--phases", str(phases))
    # Refused after the fleet file loads and before the daemon opens a session or a model.
    _assert_one_line(*_cli(*args), f"--phases {phases}", DUPLICATE)


def test_sim_refuses_a_trace_with_a_key_given_twice(tmp_path: Path) -> None:
    trace = _write(tmp_path, TRACE, "trace.yaml")
    args = ("sim", "--policy", "elastic", "--trace", str(trace), "--profile", str(PROFILE))
    _assert_one_line(*_cli(*args), f"trace {trace}", DUPLICATE)


# -- the one ValidationError wording ---------------------------------------------------------------
class _Phase(BaseModel):
    model_config = ConfigDict(extra="forbid")

    frames: int = Field(gt=0)
    uplink_mbit: float | None = None


class _File(BaseModel):
    model_config = ConfigDict(extra="forbid")

    phases: list[_Phase]


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        ({"phases": [{"frames": 0}]}, "phases[0].frames: Input should be greater than 0 (got 0)"),
        ({"phases": [{}]}, "phases[0].frames: required key is missing"),
        (
            {"phases": [{"frames": 1, "uplnk_mbit": 2}]},
            "phases[0].uplnk_mbit: unknown key; did you mean 'uplink_mbit'?",
        ),
        (
            {"phases": [{"frames": "x" * 100}]},
            f"phases[0].frames: Input should be a valid integer, unable to parse string as an "
            f"integer (got '{'x' * 36}...)",
        ),
    ],
)
def test_validation_errors_are_worded_one_way(data: dict[str, Any], expected: str) -> None:
    with pytest.raises(ValidationError) as caught:
        _File.model_validate(data)
    assert format_validation_error(caught.value, _File) == expected
