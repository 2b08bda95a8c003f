"""`elasticfog bench`: bad input is one line, a short glitch run keeps its JSON contract, and a
bench interrupted with Ctrl-C leaves no namespace, qdisc, cgroup or process behind.

The option checks run anywhere (no testbed is built for bad input); the runs need root.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from common.cli import app
from deploy.procs import elasticfog_argv
from deploy.testbed import Testbed
from tests.e2e.conftest import processes_under, remains_of_testbed
from tests.helpers.gates import root_only

pytestmark = pytest.mark.e2e


SMALL = ["--input-shape", "3x64x64", "--no-plots"]
INTERRUPT_WAIT_S = 30.0
"""Bound of the wait for an interrupted bench to clean up and exit."""
FRAMES_SEEN_WAIT_S = 60.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["glitch", "--from-mbit", "0", "--to-mbit", "1"], "must be a positive number"),
        (["glitch", "--from-mbit", "10", "--to-mbit", "1", "--policies", "nope"], "unknown nope"),
        (["table1", "--uplinks", "1,fast"], "'fast' is not a number"),
        (["table3", "--robot-cpu", "0"], "--robot-cpu 0: expected 0.01 to 16"),
        (["table2", "--frames", "0"], "--frames 0: expected at least 1"),
        (["anycast", "--input-shape", "3xbig"], "bad shape '3xbig'"),
        (["table1", "--name", "Bad_Name"], "bad testbed name 'Bad_Name'"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    result = CliRunner().invoke(app, ["bench", *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output


def test_without_root_it_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    result = CliRunner().invoke(app, ["bench", "glitch", "--from-mbit", "10", "--to-mbit", "1"])
    assert result.exit_code == 2
    assert "the testbed needs root" in result.output


def _leftovers(name: str, workdir: Path) -> list[str]:
    return remains_of_testbed(name) + processes_under(workdir)


def _root_qdiscs() -> list[str]:
    out = subprocess.run(["tc", "qdisc", "show"], capture_output=True, text=True, check=True)
    return sorted(
        " ".join(w for w in line.split() if not w.startswith("refcnt"))
        for line in out.stdout.splitlines()
    )


@pytest.mark.usefixtures("e2e_cache")
@pytest.mark.netns
@root_only
def test_glitch_json_contract_and_nothing_lost(tmp_path: Path) -> None:
    name = f"bj{os.getpid() % 100000}"
    done = subprocess.run(
        [
            *elasticfog_argv(),
            *("bench", "glitch", "--from-mbit", "20", "--to-mbit", "1"),
            *("--policies", "elastic", "--frames", "24", "--robot-cpu", "0.5", "--json"),
            *("--name", name, "--workdir", str(tmp_path / "w"), *SMALL),
        ],
        capture_output=True,
        text=True,
        timeout=80,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    (row,) = out["results"]
    assert row["policy"] == "elastic"
    for key in ("before_mean_latency_s", "on_mean_latency_s", "after_mean_latency_s"):
        assert isinstance(row[key], float) and row[key] > 0
    assert row["settle_frames"] is None or row["settle_frames"] >= 0
    assert row["lost"] == 0
    assert not _leftovers(name, tmp_path)


@pytest.mark.usefixtures("e2e_cache")
@pytest.mark.netns
@root_only
def test_ctrl_c_during_a_bench_leaves_nothing_behind(tmp_path: Path) -> None:
    name = f"bc{os.getpid() % 100000}"
    workdir = tmp_path / "w"
    qdiscs = _root_qdiscs()
    bench = subprocess.Popen(
        [
            *elasticfog_argv(),
            *("bench", "table1", "--uplinks", "2", "--policies", "robot", "--frames", "100000"),
            *("--robot-cpu", "0.5", "--name", name, "--workdir", str(workdir), *SMALL),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # our Ctrl-C goes to the bench alone, as a terminal's would
    )
    try:
        # Interrupt it mid-run: once the robot, with its CPU quota and uplink cap, has reported
        # a few frames (all daemons, the shaping and the cgroup are in place by then).
        deadline = time.monotonic() + FRAMES_SEEN_WAIT_S
        while True:
            lines = sum(len(p.read_text().splitlines()) for p in workdir.glob("*/robot-1*.jsonl"))
            if lines >= 3:
                break
            assert bench.poll() is None, bench.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "the bench's robot reported no frame"
            time.sleep(0.1)
        assert _leftovers(name, workdir), "nothing was running: the check below would mean nothing"
        os.kill(bench.pid, signal.SIGINT)
        _, err = bench.communicate(timeout=INTERRUPT_WAIT_S)
    finally:
        if bench.poll() is None:
            os.killpg(bench.pid, signal.SIGKILL)
            bench.communicate()
        # Read, then remove, what is left: a failed run must not leave daemons loading the host.
        leftovers = _leftovers(name, workdir)
        if leftovers:
            Testbed(name).down()
    assert bench.returncode == 130, err[-3000:]
    assert "interrupted" in err
    assert not leftovers
    assert _root_qdiscs() == qdiscs
