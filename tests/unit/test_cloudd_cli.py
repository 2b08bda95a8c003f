"""`elasticfog cloud`: bad input is one line naming the problem and exit code 2 (no daemon runs)."""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cloudd.cli import fault_from_flags
from common.cli import app
from common.errors import UserError
from common.wire.registry import FaultSpec

CASES = Path(__file__).resolve().parents[1] / "config_cases"


@pytest.fixture(autouse=True)
def restore_logging() -> Iterator[None]:
    """The command configures the root logger (as a process would); undo it for other tests."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield
    finally:
        for handler in list(root.handlers):
            if handler not in handlers:
                root.removeHandler(handler)
        for handler in handlers:
            if handler not in root.handlers:
                root.addHandler(handler)
        root.setLevel(level)


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    return Path(shutil.copy(CASES / "valid-single-host.yaml", tmp_path / "fleet.yaml"))


def invoke(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["cloud", *args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, result.output


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--id", "edge-9"], ["edge-9", "edge-1", "edge-2"]),
        (["--id", "robot-1"], ["robot-1", "robot machine", "edge-1"]),
        (["--id", "edge-1", "--inject-drop", "1.5"], ["--inject-drop", "[0, 1]"]),
        (["--id", "edge-1", "--inject-delay-ms", "-3"], ["--inject-delay-ms", ">= 0"]),
        (["--id", "edge-1", "--log-level", "loud"], ["--log-level", "'loud'"]),
    ],
    ids=["unknown-id", "robot-id", "drop", "delay", "log-level"],
)
def test_bad_input_exits_2_naming_it(fleet: Path, args: list[str], needles: list[str]) -> None:
    code, output = invoke("--config", str(fleet), *args)
    assert code == 2, output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in output, (needle, output)


def test_missing_config_file_is_named(tmp_path: Path) -> None:
    code, output = invoke("--config", str(tmp_path / "nope.yaml"), "--id", "edge-1")
    assert code == 2 and "nope.yaml" in output


def test_flags_override_the_configured_faults() -> None:
    assert fault_from_flags(10.0, 0.5, True, None, None) == FaultSpec(
        delay_ms=10.0, drop=0.5, stall=True
    )
    assert fault_from_flags(10.0, 0.5, False, 250.0, 0.0) == FaultSpec(delay_ms=250.0)
    with pytest.raises(UserError, match="inject-delay-ms inf"):
        fault_from_flags(0.0, 0.0, False, float("inf"), None)
