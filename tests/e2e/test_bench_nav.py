"""`elasticfog bench nav`: bad input is one line, and a quick run at the smallest settings (real
registry, cloud and robot daemons on the testbed, then the closed loop) keeps its JSON contract
with no frame lost and leaves no namespace or process behind.

The option checks run anywhere; the run needs root.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

from common.cli import app
from deploy.procs import elasticfog_argv
from tests.e2e.conftest import processes_under, remains_of_testbed
from tests.helpers.gates import root_only

pytestmark = pytest.mark.e2e


CONTRACT = {
    "option",
    "resolution",
    "update_hz",
    "t_o_s",
    "t_p_s",
    "t_c_s",
    "t_f_s",
    "collisions",
    "maneuvers",
    "lost",
}
RUN_TIMEOUT_S = 90
FRAMES = 16
"""Enough that frames remain after the ones run before the CPU quota and the warm-up."""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--options", "1,5"], "--options: unknown '5'"),
        (["--resolutions", "640"], "'640' is not WIDTHxHEIGHT"),
        (["--resolutions", "16x12"], "outside"),
        (["--uplink-mbit", "0"], "must be a positive number"),
        (["--laps", "0"], "--laps 0: expected at least 1"),
        (["--table5", "real"], "--table5: expected sim or live"),
        (["--robot-cpu", "0"], "--robot-cpu 0: expected 0.01 to 16"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    result = CliRunner().invoke(app, ["bench", "nav", *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output


@pytest.mark.netns
@root_only
def test_quick_json_contract_and_nothing_lost(tmp_path: Path) -> None:
    name = f"bn{os.getpid() % 100000}"
    done = subprocess.run(
        [
            *elasticfog_argv(),
            *("bench", "nav", "--quick", "--json", "--no-plots"),
            *("--resolutions", "160x120", "--options", "1,4,off", "--frames", str(FRAMES)),
            *("--name", name, "--workdir", str(tmp_path / "w")),
        ],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    # The contract: the option rows, and what each image codec does to zoo:stereo's answers.
    assert set(out) == {"results", "fidelity"}
    assert out["fidelity"], "bench nav --json has no codec fidelity rows"
    for fid in out["fidelity"]:
        assert fid["size"] == "160x120"
        assert 0 <= fid["disparity_bad1_share"] <= 1
        assert isinstance(fid["passes"], bool)
    rows = {row["option"]: row for row in out["results"]}
    assert sorted(rows, key=str) == [1, 4, "off"]
    for option, row in rows.items():
        assert set(row) == CONTRACT
        assert row["resolution"] == "160x120"
        assert row["lost"] == 0
        assert row["maneuvers"] == 7  # one lap of the circuit
        assert 0 <= row["collisions"] <= row["maneuvers"]
        if option == "off":
            assert row["update_hz"] is None and row["t_f_s"] is None
            continue
        assert row["update_hz"] > 0
        assert row["t_f_s"] > 0 and row["t_c_s"] > 0
    assert rows[1]["t_o_s"] > 0 and rows[1]["t_p_s"] > 0  # offloaded: network and cloud time
    assert rows[4]["t_o_s"] == 0 and rows[4]["t_p_s"] == 0  # all on the robot
    # Without the assistant the joystick drives into every obstacle.
    assert rows["off"]["collisions"] == rows["off"]["maneuvers"]
    assert not remains_of_testbed(name) + processes_under(tmp_path)
