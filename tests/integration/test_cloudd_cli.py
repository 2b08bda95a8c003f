"""`elasticfog cloud` as a real subprocess: ready on its liveliness token, fault flags applied,
SIGUSR1 dumps its threads without stopping it, and SIGINT or SIGTERM stop it within 2 s with exit
code 0 (sessions closed, no hang)."""

from __future__ import annotations

import signal
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import yaml

from common import keys
from common.wire import decode
from common.wire.registry import ProbeReply, ProbeRequest
from deploy.procs import elasticfog_argv
from tests.integration.conftest import Router
from tests.unit.test_cloudd_validate import write_tiny_model

STOP_WITHIN_S = 2.0
START_WITHIN_S = 60.0
INJECTED_DELAY_MS = 200.0


@pytest.fixture
def fleet_file(tmp_path: Path, zenoh_router: Router) -> Path:
    model = write_tiny_model(tmp_path / "tiny.onnx")
    data = {
        "fleet": f"cli-{uuid.uuid4().hex[:8]}",
        "service": "vision",
        "model": str(model),
        "registry": {"endpoint": zenoh_router.endpoint, "listen": [zenoh_router.endpoint]},
        "machines": {
            "edge-1": {"role": "cloud", "listen": ["tcp/127.0.0.1:0"]},
            "robot-1": {"role": "robot", "listen": ["tcp/127.0.0.1:0"]},
        },
        "initial_policy": {"edge-1": "service"},
        "latency_bound": {"seconds": 0.5},
        "deadline_s": 1.0,
    }
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.fixture
def start_daemon(
    fleet_file: Path, tmp_path: Path
) -> Iterator[Callable[..., tuple[subprocess.Popen[bytes], Path]]]:
    procs: list[subprocess.Popen[bytes]] = []

    def start(*args: str) -> tuple[subprocess.Popen[bytes], Path]:
        log_path = tmp_path / f"edge-1.{len(procs)}.log"
        with log_path.open("wb") as log_file:
            proc = subprocess.Popen(
                [*elasticfog_argv(), "cloud", "--config", str(fleet_file), "--id", "edge-1", *args],
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        procs.append(proc)
        return proc, log_path

    try:
        yield start
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_daemon_serves_then_stops_within_2s(
    start_daemon, fleet_file: Path, zenoh_router: Router, open_peer, wait_for_token, sig: int
) -> None:
    fleet = yaml.safe_load(fleet_file.read_text())["fleet"]
    proc, log_path = start_daemon("--inject-delay-ms", str(INJECTED_DELAY_MS))
    session = open_peer()
    wait_for_token(session, keys.alive_deployment(fleet, "edge-1"), timeout_s=START_WITHIN_S)

    request = ProbeRequest(sender="test", sent_at=time.time()).to_wire()
    t0 = time.monotonic()
    replies = [
        decode(r.ok.payload.to_bytes())
        for r in session.get(keys.dep_probe(fleet, "edge-1"), payload=request, timeout=5.0)
        if r.ok is not None
    ]
    took_ms = (time.monotonic() - t0) * 1000
    assert len(replies) == 1 and isinstance(replies[0], ProbeReply), replies
    assert replies[0].fault.delay_ms == INJECTED_DELAY_MS
    assert took_ms >= INJECTED_DELAY_MS, f"--inject-delay-ms not applied ({took_ms:.0f} ms)"

    proc.send_signal(signal.SIGUSR1)  # dumps the threads' stacks to the log, changes nothing
    again = session.get(keys.dep_probe(fleet, "edge-1"), payload=request, timeout=5.0)
    assert [r for r in again if r.ok is not None], "still serving after SIGUSR1"

    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        code = proc.wait(timeout=STOP_WITHIN_S + 3)
    except subprocess.TimeoutExpired:
        pytest.fail(f"edge-1 did not stop:\n{log_path.read_text()[-3000:]}")
    took = time.monotonic() - t0
    log = log_path.read_text()
    assert code == 0, log[-3000:]
    assert took <= STOP_WITHIN_S, f"stopped {took:.2f} s after {signal.Signals(sig).name}"
    assert "Traceback" not in log, log[-3000:]
    assert "edge-1: stopped" in log
    assert "most recent call first" in log, "SIGUSR1 wrote no thread dump"
    if sig == signal.SIGTERM:
        assert "draining" in log
