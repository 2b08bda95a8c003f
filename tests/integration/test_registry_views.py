"""The routing-state CLI (`routes`, `deployments`, `robots`, `events`, `watch`) against a real
registry over Zenoh (client sessions, loopback), and `elasticfog registry` itself: views print
the state, `--json` is plain JSON, an unreachable registry is exit 2 with the endpoint named, a
registry started as a subprocess stops on SIGTERM within 2 s."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh
from typer.testing import CliRunner

from common import keys
from common.cli import app
from common.config import FleetConfig
from common.session import open_session
from tests.helpers import registry as reg
from tests.helpers.registry import ROBOT, Fleet, RunningRegistry, wait_view, write_fleet
from tests.integration.conftest import find_free_port, loopback_endpoint

# The registry fixtures, shared with test_registry.py.
fleet = reg.fleet
peer = reg.peer
routed = reg.routed
start_registry = reg.start_registry

STOP_WITHIN_S = 2.0
START_TIMEOUT_S = 30.0


def _invoke(*args: str) -> tuple[int, str, str]:
    # Wide enough that no table cell wraps.
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.stdout, result.stderr


def _connect(fleet_cfg: FleetConfig) -> list[str]:
    return ["--connect", fleet_cfg.registry.endpoint, "--fleet", fleet_cfg.fleet]


def test_views_print_the_routing_state(routed: Fleet, tmp_path: Path) -> None:
    cfg = routed.cfg
    routed.robot.frame_done("edge-1", 0.02)
    code, out, err = _invoke("routes", *_connect(cfg))
    assert code == 0, err
    assert ROBOT in out and "edge-1" in out and "initial" in out

    code, out, err = _invoke("routes", *_connect(cfg), "--json")
    assert code == 0, err
    [route] = json.loads(out)
    assert (route["robot"], route["deployment"], route["epoch"]) == (ROBOT, "edge-1", 1)

    code, out, err = _invoke("deployments", *_connect(cfg), "--json")
    assert code == 0, err
    deployments = {d["id"]: d for d in json.loads(out)}
    assert deployments["edge-1"]["states"] == {ROBOT: "service"}
    assert deployments["edge-2"]["alive"] is True
    # Load and capacity as the deployments report them (the fake reports 0 of 4).
    assert (deployments["edge-1"]["load"], deployments["edge-1"]["capacity"]) == (0, 4)

    code, out, err = _invoke("robots", *_connect(cfg), "--json")
    assert code == 0, err
    [robot] = json.loads(out)
    assert (robot["deployment"], robot["bound_stat"], robot["extra"]["state"]) == (
        "edge-1",
        "median",
        "service",
    )
    # Why the robot is where it is: its last route event.
    assert robot["reason"] == "initial: local -> edge-1"

    code, out, err = _invoke("events", *_connect(cfg), "--limit", "3", "--json")
    assert code == 0, err
    assert len(json.loads(out)) == 3

    code, out, err = _invoke("deployments", *_connect(cfg))
    assert code == 0 and "edge-2" in out and "standby" not in out, out
    assert "capacity" in out, out

    code, out, err = _invoke("robots", *_connect(cfg))
    assert code == 0 and "reason" in out and "initial: local -> edge-1" in out, out

    # --config: the file names the endpoint and the fleet.
    config = cfg.source_path
    assert config is not None
    code, out, err = _invoke("events", "--config", str(config))
    assert code == 0 and "route" in out and "deployment_up" in out, err


def test_watch_shows_robots_with_their_deployment_window_and_cut(routed: Fleet) -> None:
    robot = routed.robot
    for _ in range(5):
        robot.frame_done("edge-1", 0.02)
    wait_view(
        routed.observer,
        routed.cfg,
        "robots",
        lambda rows: rows[0].window_len == 5 and rows[0].action == "cut:1",
        "the robot's frames",
    )
    code, out, err = _invoke("watch", *_connect(routed.cfg), "--count", "1")
    assert code == 0, err
    for needle in (ROBOT, "edge-1", "service", "cut:1", "ms / 100.0 ms median"):
        assert needle in out, (needle, out)


def _assert_unreachable(err: str, endpoint: str, hint: str) -> None:
    """One line naming the endpoint and what to start, without zenoh's own text (guards against
    `Unable to connect to any of [Single(tcp/...)]. Timeout!` reaching the user)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0] == f"error: cannot reach {endpoint}: nothing answers there; {hint}", lines[0]
    assert "Single(" not in err and "Unable to connect" not in err, err


def test_views_exit_2_naming_an_unreachable_endpoint(tmp_path: Path) -> None:
    endpoint = loopback_endpoint(find_free_port())
    hint = "start `elasticfog registry` there (it hosts the fleet's router), or check the endpoint"
    t0 = time.monotonic()
    for command in ("routes", "robots", "watch"):  # deployments and events share the path
        code, out, err = _invoke(command, "--connect", endpoint)
        assert code == 2, (command, out, err)
        assert out == "" and "Traceback" not in err, (command, err)
        _assert_unreachable(err, endpoint, hint)
    assert time.monotonic() - t0 < 20

    config, cfg = write_fleet(tmp_path)  # nobody listens on its endpoint either
    code, _, err = _invoke("routes", "--config", str(config))
    assert code == 2, err
    hint = (
        f"start `elasticfog registry --config {config}` there (it hosts the fleet's router), "
        f"or check registry.endpoint in {config}"
    )
    _assert_unreachable(err, cfg.registry.endpoint, hint)


def test_a_router_without_a_registry_is_exit_2_after_the_timeout() -> None:
    endpoint = loopback_endpoint(find_free_port())
    router = open_session(router=True, listen=[endpoint])
    try:
        code, out, err = _invoke("robots", "--connect", endpoint, "--timeout", "0.5")
    finally:
        router.close()
    assert code == 2 and out == ""
    assert "no reply from the registry of fleet 'default' at " + endpoint in err


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        ([], "--config FILE"),
        (["--connect", "127.0.0.1:7447"], "--connect"),
        (["--connect", "tcp/127.0.0.1:7447", "--fleet", "a/b"], "--fleet"),
        (["--config", "/nonexistent/fleet.yaml"], "/nonexistent/fleet.yaml"),
    ],
)
def test_bad_view_options_are_one_line_and_exit_2(args: list[str], needle: str) -> None:
    code, _, err = _invoke("routes", *args)
    assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err


def test_registry_command_refuses_a_bad_config_and_a_busy_port(
    tmp_path: Path,
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
) -> None:
    code, _, err = _invoke("registry", "--config", str(tmp_path / "missing.yaml"))
    assert code == 2 and "missing.yaml" in err
    path, cfg = fleet
    start_registry(cfg)
    code, _, err = _invoke("registry", "--config", str(path), "--db", str(tmp_path / "b.sqlite"))
    assert code == 2 and cfg.registry.endpoint in err, err


def test_registry_subprocess_stops_on_sigterm_within_2s(
    fleet: tuple[Path, FleetConfig], peer: Callable[[FleetConfig], zenoh.Session]
) -> None:
    path, cfg = fleet
    proc = subprocess.Popen(
        [sys.executable, "-c", "from common.cli import main; main()", "registry", "-c", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env=dict(os.environ),
    )
    try:
        observer = peer(cfg)
        seen = _token_seen(observer, keys.alive_registry(cfg.fleet, cfg.registry.id))
        assert seen, _output(proc)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=10)
        took_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    log = _output(proc)
    assert code == 0, log
    assert took_s <= STOP_WITHIN_S, f"stopped after {took_s:.2f} s"
    assert "Traceback" not in log and "registry registry stopped" in log, log


def _token_seen(session: zenoh.Session, key: str) -> bool:
    seen = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            seen.set()

    sub = session.liveliness().declare_subscriber(key, on_sample, history=True)
    try:
        return seen.wait(START_TIMEOUT_S)
    finally:
        sub.undeclare()


def _output(proc: subprocess.Popen[bytes]) -> str:
    if proc.poll() is None or proc.stdout is None:
        return "(still running)"
    return proc.stdout.read().decode(errors="replace")
