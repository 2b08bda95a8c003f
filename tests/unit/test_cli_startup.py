"""`elasticfog --help` stays light: building the whole CLI from its entry points, and printing the
help of the root, of `routes` and of `model`, imports none of the heavy libraries (numpy, pydantic,
zenoh, onnxruntime, onnx, cv2, ...). Guards against a register module importing one at module
level again, which made `elasticfog --help` take half a second. Behaviour only, no timings:
benchmarks/cli_startup.py measures the time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("numpy", "pydantic", "zenoh", "onnxruntime", "onnx", "cv2", "matplotlib", "skimage")
# Every top-level command the entry points register (names are a contract).
COMMANDS = (
    "bench",
    "cloud",
    "demo",
    "deployments",
    "events",
    "init",
    "model",
    "registry",
    "robot",
    "robots",
    "routes",
    "sim",
    "testbed",
    "watch",
)
# A fresh interpreter builds the app (what every command does first), runs it with its argv when
# given, then prints the heavy modules it imported.
BUILD = "import json, sys\nfrom common.cli import app\n"
RUN = """
try:
    app(sys.argv[1:], prog_name="elasticfog")
except SystemExit as exc:
    assert exc.code in (0, None), exc.code
"""
REPORT = f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))\n"


def _env() -> dict[str, str]:
    return {**os.environ, "COLUMNS": "200"}


def _elasticfog() -> list[str]:
    script = Path(sys.executable).with_name("elasticfog")
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "from common.cli import main; main()"]


def _run(argv: list[str]) -> subprocess.CompletedProcess[str]:
    """A fresh interpreter in the repository, with the test environment."""
    return subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, env=_env(), timeout=60)


@pytest.mark.parametrize("args", [[], ["--help"], ["routes", "--help"], ["model", "--help"]])
def test_help_imports_no_heavy_library(args: list[str]) -> None:
    # []: only the import of common.cli, which registers every command.
    code = BUILD + (RUN if args else "") + REPORT
    done = _run([sys.executable, "-c", code, *args])
    assert done.returncode == 0, done.stderr
    imported = json.loads(done.stdout.strip().splitlines()[-1])
    assert imported == [], f"`elasticfog {' '.join(args)}` imported {imported}"


def test_help_exits_zero_and_lists_every_command() -> None:
    done = _run([*_elasticfog(), "--help"])
    assert done.returncode == 0, done.stderr
    words = set(done.stdout.replace("│", " ").split())
    missing = [name for name in COMMANDS if name not in words]
    assert not missing, f"not in `elasticfog --help`: {missing}\n{done.stdout}"


@pytest.mark.parametrize("flag", ["--version", "-V"])
def test_version_prints_the_package_version_and_imports_nothing_heavy(flag: str) -> None:
    from importlib.metadata import version

    done = _run([*_elasticfog(), flag])
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"elasticfog {version('elasticfog')}"
    code = BUILD + RUN + REPORT
    imported = json.loads(_run([sys.executable, "-c", code, flag]).stdout.strip().splitlines()[-1])
    assert imported == []


def test_help_texts_are_paragraphs_wrapped_by_the_terminal_not_the_source() -> None:
    import typer.main

    from common.cli import app, as_paragraphs

    assert as_paragraphs("one\n    two\n\n    three\n") == "one two\n\nthree"
    helps: list[tuple[str, str]] = []

    def walk(command: Any, path: str) -> None:
        helps.append((path, command.help or ""))
        for sub_name, sub in getattr(command, "commands", {}).items():
            walk(sub, f"{path} {sub_name}")

    walk(typer.main.get_command(app), "elasticfog")
    wrapped = [path for path, text in helps if any("\n" in p for p in text.split("\n\n"))]
    assert not wrapped, f"help wrapped mid-paragraph: {wrapped}"
