"""Starting and stopping the runtime: signals, the demo, and bad input at the command line.

Daemons stop on SIGINT/SIGTERM within 2 s (a serving cloud daemon drains first: the registry
moves its robot, no frame lost); `elasticfog demo` leaves no process behind, also when
interrupted; bad configs and an unreachable registry give exit code 2 and one line naming the
problem, never a traceback.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import time
import uuid
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml

from deploy.demo import answered_by, read_telemetry
from deploy.procs import elasticfog_argv, free_tcp_port
from deploy.readiness import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
WAIT_S = 30.0
STOP_WITHIN_S = 2.0
"""The daemons' promise: stopped this soon after SIGINT/SIGTERM."""
DEMO_KEYS = {
    "policy",
    "tls",
    "frames",
    "answered",
    "lost",
    "fallbacks",
    "by_deployment",
    "actions",
    "mean_latency_s",
    "p95_latency_s",
    "failovers",
    "phases",
    "wall_s",
}
MARKER_ENV = "ELASTICFOG_TEST_MARKER"
"""Set in the demo's environment; its daemons inherit it, which is how we find leftovers."""


def test_daemons_stop_on_sigint_and_sigterm_within_2s(make_fleet, local_fleet, tmp_path: Path):
    fleet = make_fleet()
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1", "edge-2"])
    tap = lf.tap(ROBOT)
    telemetry = tmp_path / "robot-1.jsonl"
    robot = lf.start_robot(ROBOT, "--policy", "cloud", telemetry=telemetry)
    tap.wait_for(
        lambda r: answered_by(r) == "edge-1", timeout_s=WAIT_S, what="edge-1 serving", procs=[robot]
    )

    # The serving cloud drains on SIGTERM: the registry moves the robot first, nothing is lost.
    edge1 = lf.latest("edge-1")
    asked_at = time.time()
    stopped = edge1.stop(grace_s=10.0, sig=signal.SIGTERM)
    assert not stopped.killed and stopped.returncode == 0, edge1.log_tail()
    assert stopped.stop_s <= STOP_WITHIN_S, f"edge-1 took {stopped.stop_s:.2f} s to drain"
    tap.wait_for(
        lambda r: r["at"] >= asked_at and answered_by(r) == "edge-2",
        timeout_s=WAIT_S,
        what="edge-2 serving after edge-1 drained",
        procs=[robot],
    )

    for name, sig in (
        (ROBOT, signal.SIGINT),
        ("edge-2", signal.SIGTERM),
        ("registry", signal.SIGINT),
    ):
        proc = lf.latest(name)
        result = proc.stop(grace_s=10.0, sig=sig)
        assert not result.killed and result.returncode == 0, f"{name}:\n{proc.log_tail()}"
        assert result.stop_s <= STOP_WITHIN_S, f"{name} took {result.stop_s:.2f} s"

    records = read_telemetry(telemetry)
    frames = sorted(r["frame"] for r in records)
    assert frames == list(range(len(frames))), "a frame was lost around the drain"


def _marked_processes(marker: str) -> list[psutil.Process]:
    found = []
    for proc in psutil.process_iter(["pid"]):
        try:
            if proc.environ().get(MARKER_ENV) == marker:
                found.append(proc)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return found


def _demo_env() -> tuple[str, dict[str, str]]:
    """A marker and the environment carrying it (with the e2e model cache)."""
    marker = uuid.uuid4().hex
    env = dict(os.environ, **{MARKER_ENV: marker})
    return marker, env


@pytest.fixture(scope="module")
def demo_model(e2e_cache: Path) -> str:
    """The demo's model (`elasticfog init`'s) split into the test cache once: the demo would do
    it too, inside the time its test is given."""
    from common.init_cli import DEFAULT_MODEL
    from common.partition import load_partition

    load_partition(DEFAULT_MODEL)
    return DEFAULT_MODEL


def test_demo_fails_over_and_leaves_no_process(e2e_cache: Path, demo_model: str):
    marker, env = _demo_env()
    frames = 40
    done = subprocess.run(
        [*elasticfog_argv(), "demo", "--frames", str(frames), "--kill-service-at", "15", "--json"],
        env=env,
        capture_output=True,
        text=True,
        timeout=80,
    )
    leftovers = _marked_processes(marker)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout)
    assert set(summary) == DEMO_KEYS
    assert summary["frames"] == frames and summary["lost"] == 0
    assert len(summary["failovers"]) == 1
    failover = summary["failovers"][0]
    assert failover["from"] == "edge-1" and failover["to"] == "edge-2"
    assert failover["at_frame"] >= 15 and failover["ms"] is not None and failover["ms"] > 0
    assert sum(summary["actions"].values()) == frames
    assert summary["answered"] == sum(summary["by_deployment"].values())
    assert not leftovers, [p.cmdline() for p in leftovers]


def test_interrupted_demo_leaves_no_process(e2e_cache: Path, demo_model: str):
    marker, env = _demo_env()
    demo = subprocess.Popen(
        [*elasticfog_argv(), "demo", "--frames", "100000", "--json"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,  # as a terminal would: Ctrl-C reaches the demo, not its daemons
    )
    try:

        def robot_running() -> bool:
            return any(
                "robot" in p.cmdline() and p.pid != demo.pid for p in _marked_processes(marker)
            )

        wait_until(robot_running, timeout_s=60, what="the demo's robot", interval_s=0.2)
        demo.send_signal(signal.SIGINT)
        _, err = demo.communicate(timeout=30)
        assert demo.returncode == 130, err.decode()[-2000:]
        assert b"Traceback" not in err
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
        # Read, then end, what is left: the daemons run in sessions of their own, and a failed
        # run must not leave a fleet loading the host for the tests after it.
        leftovers = _marked_processes(marker)
        for proc in leftovers:
            with contextlib.suppress(psutil.Error):
                proc.kill()
    assert not leftovers, [p.cmdline() for p in leftovers]


# -- bad input at the command line -----------------------------------------------------------------
def _cli(*args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*elasticfog_argv(), *args], capture_output=True, text=True, timeout=timeout_s
    )


def _assert_one_line_error(done: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stdout[-1000:], done.stderr[-2000:])
    assert "Traceback" not in done.stderr, done.stderr
    for needle in needles:
        assert needle in done.stderr, (needle, done.stderr)


def _edit(path: Path, fn: Any) -> Path:
    data = yaml.safe_load(path.read_text())
    fn(data)
    out = path.with_name("bad.yaml")
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


@pytest.mark.parametrize(
    ("case", "command", "needles"),
    [
        (
            "unknown key",
            ["cloud", "--id", "edge-1"],
            ["bad.yaml", "machines.edge-1", "wrokers"],
        ),
        ("wrong type", ["registry"], ["bad.yaml", "latency_bound.seconds"]),
        ("unknown deployment id", ["cloud", "--id", "edge-9"], ["edge-9", "edge-1"]),
        ("unknown robot id", ["robot", "--id", "robot-9"], ["robot-9", "robot-1"]),
    ],
)
def test_bad_config_exits_2_naming_the_problem(
    make_fleet, case: str, command: list[str], needles: list[str]
):
    fleet = make_fleet()
    edits = {
        "unknown key": lambda d: d["machines"]["edge-1"].update(wrokers=2),
        "wrong type": lambda d: d["latency_bound"].update(seconds="fast"),
    }
    config = _edit(fleet.config, edits.get(case, lambda d: None))
    _assert_one_line_error(_cli(command[0], "--config", str(config), *command[1:]), *needles)


def test_views_exit_2_naming_an_unreachable_registry(make_fleet):
    fleet = make_fleet()
    done = _cli("routes", "--config", str(fleet.config))
    _assert_one_line_error(done, fleet.endpoint)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    t0 = time.monotonic()
    done = _cli("deployments", "--connect", endpoint, "--json")
    _assert_one_line_error(done, endpoint)
    assert time.monotonic() - t0 < 20
    assert done.stdout == ""
