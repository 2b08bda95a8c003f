"""`elasticfog bench pool`: bad input is one line, and a quick run at the smallest settings (real
registry, cloud and robot daemons on the testbed, pools of 1 and 2 round-robin deployments, then
a pool of 2 beside a standby with one member killed) keeps its JSON contract, loses no frame,
has both members of the pool of 2 answer frames and leaves no namespace or process behind.

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


ROW_KEYS = {
    "pool_size",
    "resolution",
    "max_in_flight",
    "pool",
    "frames",
    "update_hz",
    "t_o_s",
    "t_p_s",
    "t_c_s",
    "t_f_s",
    "p_needed",
    "answered_by",
    "fallbacks",
    "lost",
    "duplicates",
    "offloaded",
    "served_by_cloud",
    "served_sum",
    "computed_in_log",
    "each_frame_once",
}
RUN_TIMEOUT_S = 300
"""Three fleets (1, 2 and 3 cloud daemons) start and stop on two cores."""
FRAMES = 24
"""Enough that frames remain after the ones run before the quotas and the warm-up, and that the
kill (after a third) leaves frames for the standby."""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--sizes", "1,x"], "--sizes: 'x' is not a pool size"),
        (["--sizes", "4"], "--sizes 4: at most 3"),
        (["--resolution", "640"], "'640' is not WIDTHxHEIGHT"),
        (["--cloud-cpu", "0"], "--cloud-cpu 0: expected 0.01 to 16"),
        (["--fps", "0"], "--fps 0: expected more than 0"),
        (["--uplink-mbit", "-1"], "--uplink-mbit -1: must be a positive number"),
        (["--robot-cpu", "0"], "--robot-cpu 0: expected 0.01 to 16"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    result = CliRunner().invoke(app, ["bench", "pool", *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output


@pytest.mark.netns
@pytest.mark.slow
@root_only
def test_quick_json_contract_both_members_answer_and_nothing_lost(tmp_path: Path) -> None:
    name = f"bp{os.getpid() % 100000}"
    done = subprocess.run(
        [
            *elasticfog_argv(),
            *("bench", "pool", "--quick", "--json"),
            *("--resolution", "160x120", "--sizes", "1,2", "--frames", str(FRAMES)),
            *("--name", name, "--workdir", str(tmp_path / "w")),
        ],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    assert set(out) == {"settings", "results", "kill"}
    rows = {row["pool_size"]: row for row in out["results"]}
    assert sorted(rows) == [1, 2]
    for size, row in rows.items():
        assert set(row) == ROW_KEYS
        assert row["resolution"] == "160x120"
        assert row["lost"] == 0
        assert row["max_in_flight"] == size
        assert row["update_hz"] > 0 and row["t_p_s"] > 0
        assert row["duplicates"] == [] and row["each_frame_once"] is True
        assert len(row["pool"]) == size
    assert rows[1]["p_needed"] >= 1
    # Round robin: both members of the pool of 2 answer frames, and their own counts add up
    # to the frames the robot offloaded.
    pair = rows[2]
    assert len(pair["answered_by"]) == 2 and min(pair["answered_by"].values()) > 0
    assert pair["served_sum"] == pair["offloaded"]
    kill = out["kill"]
    assert kill["lost"] == 0
    assert kill["killed"] in kill["pool_before"]
    assert kill["standby_joined"] is True
    assert kill["each_frame_once"] is True
    assert not remains_of_testbed(name) + processes_under(tmp_path)
