"""`elasticfog demo --tls`: a short demo (one phase, `--frames`, a kill late in it) with mutual TLS
and the access control on every link, run by the real command (registry, two cloud daemons and
the robot as subprocesses on loopback, no root).

What must hold: the JSON says `"tls": true` and keeps the demo's keys; no frame is lost, also
across the failover (the registry's ctl to edge-2 passes the access control); the fleet it wrote
is `elasticfog init --tls`'s (every endpoint `tls/127.0.0.1:PORT`, each host's certificate and
key in certs/, the folder 0700 and the keys 0600); and while the robot runs, every socket that
the demo and its daemons listen on completes a TLS handshake with the fleet's CA: nothing listens
in plaintext.
"""

from __future__ import annotations

import json
import os
import socket
import ssl
import stat
import subprocess
from pathlib import Path

import psutil
import pytest

from common.config import load_fleet
from deploy.demo import read_telemetry
from deploy.procs import elasticfog_argv
from deploy.readiness import wait_until
from tests.e2e.test_runtime_lifecycle import DEMO_KEYS

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

FRAMES = 100
KILL_AT = 80
"""Late, so the sockets are checked while edge-1 still runs (one it lost meanwhile is skipped)."""
FPS = 15
FRAMES_BEFORE_CHECK = 3
HOSTS = ("registry", "edge-1", "edge-2", "robot-1", "cli")
DEMO_TIMEOUT_S = 75.0
HANDSHAKE_TIMEOUT_S = 5.0


@pytest.fixture(scope="module")
def demo_model(e2e_cache: Path) -> str:
    """The demo's model split into the test cache once (the demo would do it inside the test's
    time otherwise)."""
    from common.init_cli import DEFAULT_MODEL
    from common.partition import load_partition

    load_partition(DEFAULT_MODEL)
    return DEFAULT_MODEL


def _handshake(address: tuple[str, int], certs: Path) -> str | None:
    """None when `address` completes a TLS handshake with the fleet CA (as the CLI), else why."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=certs / "ca.crt")
    context.load_cert_chain(certs / "cli.crt", certs / "cli.key")
    try:
        with (
            socket.create_connection(address, timeout=HANDSHAKE_TIMEOUT_S) as raw,
            context.wrap_socket(raw, server_hostname=address[0]),
        ):
            return None
    except (OSError, ssl.SSLError) as exc:
        return f"{address}: {exc}"


def _plaintext_listeners(demo: psutil.Process, certs: Path) -> tuple[int, list[str]]:
    """(processes listening, the listening sockets of the demo and its daemons that do not
    speak TLS). A process gone meanwhile (the kill) is skipped."""
    listening, problems = 0, []
    for proc in [demo, *demo.children(recursive=True)]:
        try:
            conns = proc.net_connections(kind="tcp")
        except psutil.NoSuchProcess:
            continue
        addresses = sorted({c.laddr[:2] for c in conns if c.status == psutil.CONN_LISTEN})
        listening += bool(addresses)
        for address in addresses:
            problem = _handshake(address, certs)
            if problem is not None and proc.is_running():
                problems.append(f"{' '.join(proc.cmdline()[-4:])}: {problem}")
    return listening, problems


def test_demo_with_tls_loses_nothing_and_listens_on_tls_only(
    demo_model: str, tmp_path: Path
) -> None:
    work = tmp_path / "tmp"
    work.mkdir()
    argv = [*elasticfog_argv(), "demo", "--tls", "--frames", str(FRAMES), "--fps", str(FPS)]
    argv += ["--kill-service-at", str(KILL_AT), "--policy", "cloud:jpeg80", "--json", "--keep"]
    out, err = tmp_path / "demo.out", tmp_path / "demo.err"
    with out.open("wb") as stdout, err.open("wb") as stderr:
        demo = subprocess.Popen(
            argv,
            env=dict(os.environ, TMPDIR=str(work)),  # where the kept folder goes
            stdout=stdout,
            stderr=stderr,
            start_new_session=True,
        )
    try:

        def robot_running() -> Path | str | None:
            if demo.poll() is not None:
                return "exited"
            for kept in work.glob("elasticfog-demo-*"):
                telemetry = kept / "telemetry.jsonl"
                if telemetry.is_file() and len(read_telemetry(telemetry)) >= FRAMES_BEFORE_CHECK:
                    return kept
            return None

        kept = wait_until(robot_running, timeout_s=DEMO_TIMEOUT_S, what="the robot's frames")
        assert kept != "exited", err.read_text()[-3000:]
        assert isinstance(kept, Path)
        listening, problems = _plaintext_listeners(psutil.Process(demo.pid), kept / "certs")
        assert listening >= 4, f"only {listening} processes listen"  # registry, clouds, robot
        assert not problems, problems
        code = demo.wait(DEMO_TIMEOUT_S)
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, 9)
            demo.wait()
    assert code == 0, err.read_text()[-3000:]

    summary = json.loads(out.read_text())
    assert set(summary) == DEMO_KEYS
    assert summary["tls"] is True
    assert summary["frames"] == FRAMES and summary["lost"] == 0
    (failover,) = summary["failovers"]
    assert (failover["from"], failover["to"]) == ("edge-1", "edge-2"), failover

    # The fleet is `elasticfog init --tls`'s: TLS endpoints only, a certificate per host.
    cfg = load_fleet(kept / "fleet.yaml")
    endpoints = [cfg.registry.endpoint, *cfg.registry.listen]
    endpoints += [e for m in cfg.machines.values() for e in m.listen]
    assert endpoints and all(e.startswith("tls/127.0.0.1:") for e in endpoints), endpoints
    assert cfg.mtls and cfg.access_control
    certs = kept / "certs"
    assert stat.S_IMODE(certs.stat().st_mode) == 0o700
    for host in HOSTS:
        assert cfg.tls_for(host).cert == str(certs / f"{host}.crt")
        assert stat.S_IMODE((certs / f"{host}.key").stat().st_mode) == 0o600
    logs = {p.name: p.read_text() for p in (kept / "logs").glob("*.log")}
    assert not [name for name, text in logs.items() if "Traceback" in text]
