"""`elasticfog demo --script`: a short script of three phases run by the real command (registry,
two cloud daemons and the robot as subprocesses on loopback, no root).

What must hold: `--json` keeps the demo's keys and adds `phases` (one row per phase, in order,
with the contract's keys); no frame is lost, also across the failover the last phase asks for;
the phase boundaries take effect in the robot (each telemetry line names the phase its frame
is in, and in the slow-link phase every request waits at least its bytes' time on the emulated
link, while the unpaced phases do not); `--plot` writes a PNG. A bad script is one line and
exit code 2, before anything starts.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
from pathlib import Path

import pytest

from deploy.demo import read_telemetry
from deploy.procs import elasticfog_argv
from robotd.emulation import EMULATED_LINK_BURST_BYTES
from robotd.frame_path.pacing import BITS_PER_BYTE, BITS_PER_MBIT
from tests.e2e.test_runtime_lifecycle import DEMO_KEYS

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

FRAMES_PER_PHASE = 12
SLOW_MBIT = 0.5
"""Slow enough that a JPEG frame waits ~0.1-0.3 s on the link, fast enough for the deadline."""
SCRIPT = f"""\
description: e2e, three short phases
slowdown: 2
fps: 15
phases:
  - {{name: open, frames: {FRAMES_PER_PHASE}, uplink_mbit: null}}
  - {{name: slow link, frames: {FRAMES_PER_PHASE}, uplink_mbit: {SLOW_MBIT}}}
  - {{name: failover, frames: {FRAMES_PER_PHASE}, uplink_mbit: null, kill_service: true}}
"""
PHASE_NAMES = ["open", "slow link", "failover"]
PHASE_KEYS = {
    "name",
    "uplink_mbit",
    "main_action",
    "mean_latency_s",
    "p95_latency_s",
    "bytes_up",
    "fallbacks",
}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def demo_model(e2e_cache: Path) -> str:
    """The demo's model split into the test cache once (the demo would do it inside the test's
    time otherwise)."""
    from common.init_cli import DEFAULT_MODEL
    from common.partition import load_partition

    load_partition(DEFAULT_MODEL)
    return DEFAULT_MODEL


def test_a_script_switches_phases_in_the_robot_and_loses_nothing(
    demo_model: str, tmp_path: Path
) -> None:
    script = tmp_path / "short.yaml"
    script.write_text(SCRIPT, encoding="utf-8")
    plot = tmp_path / "demo.png"
    work = tmp_path / "tmp"
    work.mkdir()
    # A fixed policy offloads every frame, so the link is on every frame's path.
    argv = [*elasticfog_argv(), "demo", "--script", str(script), "--policy", "cloud:jpeg80"]
    done = subprocess.run(
        [*argv, "--json", "--keep", "--plot", str(plot)],
        env=dict(os.environ, TMPDIR=str(work)),  # where the kept folder goes
        capture_output=True,
        text=True,
        timeout=80,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)
    assert set(summary) == DEMO_KEYS
    frames = 3 * FRAMES_PER_PHASE
    assert summary["frames"] == frames and summary["lost"] == 0
    assert summary["policy"] == "cloud:jpeg80"
    assert [p["name"] for p in summary["phases"]] == PHASE_NAMES
    assert all(set(p) >= PHASE_KEYS for p in summary["phases"])
    assert [p["uplink_mbit"] for p in summary["phases"]] == [None, SLOW_MBIT, None]
    assert all(p["main_action"] == "cut:0:jpeg80" for p in summary["phases"])
    (failover,) = summary["failovers"]
    assert failover["at_frame"] >= 2 * FRAMES_PER_PHASE
    assert failover["from"] == "edge-1" and failover["to"] == "edge-2"
    assert plot.read_bytes().startswith(PNG_MAGIC)

    (kept,) = work.glob("elasticfog-demo-*")
    records = sorted(read_telemetry(kept / "telemetry.jsonl"), key=lambda r: r["frame"])
    assert [r["frame"] for r in records] == list(range(frames))
    assert [r["phase"] for r in records] == [
        n for n in PHASE_NAMES for _ in range(FRAMES_PER_PHASE)
    ]

    # The slow link holds every request for its bytes (beyond one Ethernet frame's burst).
    slow = [r for r in records if r["phase"] == "slow link" and not r["fallback"]]
    assert len(slow) >= FRAMES_PER_PHASE - 1
    for r in slow:
        link_s = (r["bytes_up"] - EMULATED_LINK_BURST_BYTES) * BITS_PER_BYTE
        link_s /= SLOW_MBIT * BITS_PER_MBIT
        assert r["transfer_s"] >= link_s, (r["frame"], r["transfer_s"], link_s)
    open_transfer = statistics.median(r["transfer_s"] for r in records if r["phase"] == "open")
    slow_transfer = statistics.median(r["transfer_s"] for r in slow)
    assert slow_transfer > 3 * open_transfer, (open_transfer, slow_transfer)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "phases:\n  - {name: a, frames: 5, uplink: 2}\n",
            "phases[0].uplink: unknown key; did you mean 'uplink_mbit'?",
        ),
        ("phases:\n  - {name: a, frames: -5}\n", "phases[0].frames: Input should be greater"),
        (
            "phases:\n  - {name: a, frames: 5, frames: 6}\n",
            "duplicate key 'frames', first given on line 2",
        ),
    ],
)
def test_a_bad_script_is_one_line_and_exit_2(tmp_path: Path, text: str, expected: str) -> None:
    script = tmp_path / "bad.yaml"
    script.write_text(text, encoding="utf-8")
    done = subprocess.run(
        [*elasticfog_argv(), "demo", "--script", str(script)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"error: --script {script}: ") and expected in lines[0]
    assert "Traceback" not in done.stderr and done.stdout == ""
