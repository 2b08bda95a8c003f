"""e2e: the network-namespace testbed with real namespaces, veths, `tc` and cgroups (root only).

Traffic stays between the testbed's own namespaces (its private subnet); every transfer and busy
loop is bounded in bytes and in time. Rates are measured at the receiver from its own timestamps:
goodput through an htb cap is the cap minus TCP/IP/Ethernet headers (1448 of every 1514 bytes on
the wire, 0.956), so the margins below are around that figure.
"""

from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import typer
import yaml
from typer.testing import CliRunner

from common.errors import UserError
from deploy import cli as testbed_cli
from deploy.cgroups import DEFAULT_CFS_PERIOD_US, MIN_QUOTA_US, find_cpu_mount
from deploy.testbed import ETC_NETNS_DIR, NETNS_DIR, SH, Testbed, TestbedError
from tests.helpers.gates import root_only

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.netns,
    root_only,
]

HOSTS = ("registry", "robot", "edge-1", "edge-2")
DEPLOY_DIR = Path(__file__).resolve().parents[2] / "deploy"
COMPOSE_FILE = DEPLOY_DIR / "docker-compose.yml"
COMPOSE_FLEET = DEPLOY_DIR / "fleet.compose.yaml"
PORT = 5001  # the namespaces are private: no clash with anything on the machine
LINE_TIMEOUT_S = 20.0
# Goodput / cap through htb with 1514-byte frames is 0.956; allow for scheduling noise.
RATE_LOW, RATE_HIGH = 0.85, 1.02
# After a cap changes, what was queued at the old rate drains first (≤ ~0.1 s of queue).
SETTLE_S = 0.4

RECEIVER = r"""
import json, socket, sys, time
host, port, total = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
srv = socket.create_server((host, port))
srv.settimeout(20)
print(json.dumps({"ready": True}), flush=True)
conn, _ = srv.accept()
conn.settimeout(20)
got, last, deadline = 0, 0.0, time.monotonic() + 30
while got < total and time.monotonic() < deadline:
    chunk = conn.recv(1 << 16)
    if not chunk:
        break
    got += len(chunk)
    now = time.monotonic()
    if now - last >= 0.05 or got >= total:
        print(json.dumps({"t": now, "bytes": got}), flush=True)
        last = now
conn.close()
"""

SENDER = r"""
import socket, sys
host, port, total = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
conn = socket.create_connection((host, port), timeout=20)
block, sent = bytes(1 << 16), 0
while sent < total:
    n = min(len(block), total - sent)
    conn.sendall(block[:n])
    sent += n
conn.close()
"""

ECHO_SERVER = r"""
import json, socket, sys
srv = socket.create_server((sys.argv[1], int(sys.argv[2])))
srv.settimeout(10)
print(json.dumps({"ready": True}), flush=True)
conn, peer = srv.accept()
conn.settimeout(10)
data = b""
while len(data) < int(sys.argv[3]):
    chunk = conn.recv(1 << 16)
    if not chunk:
        break
    data += chunk
conn.sendall(data)
conn.close()
print(json.dumps({"peer": peer[0]}), flush=True)
"""

ECHO_CLIENT = r"""
import json, os, socket, sys
payload = os.urandom(int(sys.argv[3]))
conn = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=10)
conn.sendall(payload)
back = b""
while len(back) < len(payload):
    chunk = conn.recv(1 << 16)
    if not chunk:
        break
    back += chunk
# Loopback inside the namespace works too (zenoh may listen there).
lo = socket.create_server(("127.0.0.1", 0))
socket.create_connection(lo.getsockname(), timeout=5).close()
print(json.dumps({"echoed": back == payload, "resolved": socket.gethostbyname(sys.argv[1])}))
"""

BUSY = r"""
import json, sys, time
wall = float(sys.argv[1])
print(json.dumps({"ready": True}), flush=True)
t0, c0, n = time.monotonic(), time.process_time(), 0
while time.monotonic() - t0 < wall:
    n += 1
print(json.dumps({"cpu_s": time.process_time() - c0, "wall_s": time.monotonic() - t0}), flush=True)
"""

# Zenoh sessions configured from the compose fleet file, as the daemons open them.
ZENOH_ROUTER = r"""
import json, signal, sys, threading
from common.config import load_fleet
from common.session import open_session
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
with open_session(load_fleet(sys.argv[1]), router=True):
    print(json.dumps({"ready": True}), flush=True)
    stop.wait(30)
"""

ZENOH_SERVER = r"""
import json, signal, sys, threading
from common.config import load_fleet
from common.session import open_session
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
reply = bytes(int(sys.argv[3]))
with open_session(load_fleet(sys.argv[1]), machine=sys.argv[2]) as session:
    queryable = session.declare_queryable(
        "ef/compose/testbed-probe", lambda q: q.reply(q.key_expr, reply), complete=True
    )
    print(json.dumps({"ready": True}), flush=True)
    stop.wait(30)
    queryable.undeclare()
"""

ZENOH_CLIENT = r"""
import json, sys, time
from common.config import load_fleet
from common.session import open_session
wanted, got, deadline = int(sys.argv[3]), 0, time.monotonic() + 20
with open_session(load_fleet(sys.argv[1]), machine=sys.argv[2]) as session:
    while got < wanted and time.monotonic() < deadline:
        for reply in session.get("ef/compose/testbed-probe", timeout=5.0):
            got += reply.ok is not None
print(json.dumps({"replies": got}), flush=True)
"""

STUBBORN = r"""
import signal, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("ready", flush=True)
time.sleep(30)  # readiness-ok: stays up until the testbed kills it
"""


def _name(tag: str) -> str:
    return f"t{tag}{os.getpid() % 100000}"


def _python(tb: Testbed, host: str, code: str, *args: object) -> subprocess.Popen[str]:
    argv = [sys.executable, "-c", code, *map(str, args)]
    return tb.popen(host, argv, stdout=subprocess.PIPE, text=True)


def _lines(proc: subprocess.Popen[str], timeout_s: float = LINE_TIMEOUT_S) -> Iterator[str]:
    """The process's stdout lines, failing the test if one takes longer than timeout_s."""
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while True:
            if not sel.select(timeout_s):
                raise AssertionError(f"no output from {proc.args!r} within {timeout_s} s")
            line = proc.stdout.readline()
            if not line:
                return
            yield line


def _next_json(proc: subprocess.Popen[str]) -> dict[str, Any]:
    for line in _lines(proc):
        return dict(json.loads(line))
    raise AssertionError(f"{proc.args!r} exited (code {proc.wait(5)}) without output")


def _finish(*procs: subprocess.Popen[str]) -> None:
    for proc in procs:
        try:
            proc.wait(timeout=LINE_TIMEOUT_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
            if proc.stdout is not None:
                proc.stdout.close()


def _rate_mbit(samples: list[tuple[float, int]], start: float, end: float) -> float:
    """Goodput between the first sample at or after `start` and the last one at or before `end`."""
    window = [s for s in samples if start <= s[0] <= end]
    assert len(window) >= 3, f"too few samples between {start:.2f} and {end:.2f}: {samples}"
    (t0, b0), (t1, b1) = window[0], window[-1]
    return (b1 - b0) * 8 / (t1 - t0) / 1e6


def _transfer(
    tb: Testbed,
    src: str,
    dst: str,
    total_bytes: int,
    change_at_bytes: int | None = None,
    change: Any = None,
) -> tuple[list[tuple[float, int]], float | None]:
    """Send total_bytes src → dst; call `change()` once the receiver has counted change_at_bytes.

    Returns the receiver's (time, bytes so far) samples and the time the change was made.
    """
    receiver = _python(tb, dst, RECEIVER, tb.address(dst), PORT, total_bytes)
    sender = None
    try:
        assert _next_json(receiver) == {"ready": True}
        sender = _python(tb, src, SENDER, tb.address(dst), PORT, total_bytes)
        samples: list[tuple[float, int]] = []
        changed_at = None
        for line in _lines(receiver):
            sample = json.loads(line)
            samples.append((sample["t"], sample["bytes"]))
            if change is not None and changed_at is None and sample["bytes"] >= change_at_bytes:
                change()
                changed_at = time.monotonic()
        assert samples and samples[-1][1] == total_bytes, f"transfer incomplete: {samples[-1:]}"
        return samples, changed_at
    finally:
        _finish(receiver, *([sender] if sender else []))


def _root_snapshot() -> dict[str, Any]:
    """What the testbed must leave as it found: root-namespace links and qdiscs, and so on."""
    links = subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True, check=True)
    qdiscs = subprocess.run(["tc", "qdisc", "show"], capture_output=True, text=True, check=True)
    return {
        "links": sorted(line.split(":")[1].strip() for line in links.stdout.splitlines()),
        "qdiscs": sorted(
            " ".join(w for w in line.split() if not w.startswith("refcnt"))
            for line in qdiscs.stdout.splitlines()
        ),
    }


@pytest.fixture(scope="module")
def testbed() -> Iterator[Testbed]:
    with Testbed(_name("m"), hosts=HOSTS) as tb:
        yield tb


def test_hosts_reach_each_other_by_address_and_name(testbed: Testbed) -> None:
    addresses = testbed.addresses()
    assert list(addresses) == list(HOSTS)
    assert len(set(addresses.values())) == len(HOSTS)
    assert all(a.startswith("10.77.0.") for a in addresses.values())

    size = 64 * 1024
    server = _python(testbed, "edge-1", ECHO_SERVER, testbed.address("edge-1"), PORT, size)
    client = None
    try:
        assert _next_json(server) == {"ready": True}
        # By name: the testbed's /etc/hosts inside each namespace knows every host.
        client = _python(testbed, "robot", ECHO_CLIENT, "edge-1", PORT, size)
        result = _next_json(client)
        assert result == {"echoed": True, "resolved": testbed.address("edge-1")}
        assert _next_json(server) == {"peer": testbed.address("robot")}
    finally:
        _finish(server, *([client] if client else []))


def test_uplink_cap_limits_throughput_and_changes_while_running(testbed: Testbed) -> None:
    testbed.shape("robot", 8)
    assert testbed.link_rates("robot") == {"uplink_mbit": 8.0, "downlink_mbit": None}
    try:
        # 1 MB at 8 Mbit/s, then the cap drops to 2 Mbit/s mid-flow (a bandwidth glitch).
        samples, changed_at = _transfer(
            testbed,
            "robot",
            "edge-1",
            total_bytes=1_600_000,
            change_at_bytes=1_000_000,
            change=lambda: testbed.shape("robot", 2),
        )
    finally:
        testbed.shape("robot", None)
    assert changed_at is not None
    before = _rate_mbit(samples, samples[0][0], changed_at)
    after = _rate_mbit(samples, changed_at + SETTLE_S, samples[-1][0])
    print(f"uplink cap 8 Mbit/s: {before:.3f} Mbit/s; cap 2 Mbit/s: {after:.3f} Mbit/s")
    assert RATE_LOW * 8 <= before <= RATE_HIGH * 8
    assert RATE_LOW * 2 <= after <= RATE_HIGH * 2


def test_downlink_cap_limits_only_what_the_host_receives(testbed: Testbed) -> None:
    testbed.shape("robot", None, 4)
    try:
        assert testbed.link_rates("robot") == {"uplink_mbit": None, "downlink_mbit": 4.0}
        down_samples, _ = _transfer(testbed, "edge-1", "robot", total_bytes=1_000_000)
        up_samples, _ = _transfer(testbed, "robot", "edge-1", total_bytes=4_000_000)
    finally:
        testbed.shape("robot", None)
    down = _rate_mbit(down_samples, down_samples[0][0], down_samples[-1][0])
    up_elapsed = up_samples[-1][0] - up_samples[0][0]
    print(f"downlink cap 4 Mbit/s: {down:.3f} Mbit/s; 4 MB uplink uncapped in {up_elapsed:.3f} s")
    assert RATE_LOW * 4 <= down <= RATE_HIGH * 4
    # Uncapped, 4 MB takes well under the 8 s it would take at 4 Mbit/s.
    assert up_elapsed < 2.0


def test_cpu_fraction_caps_all_processes_of_a_host_together(testbed: Testbed) -> None:
    group = testbed.cgroup("edge-2")
    if group is None:
        pytest.skip("no cgroup-v1 cpu controller mounted")
    testbed.cpu("edge-2", 0.25)
    assert testbed.cpu_fraction("edge-2") == 0.25
    assert group.bandwidth_us() == (1250, DEFAULT_CFS_PERIOD_US)  # a 5 ms period, not 100 ms
    throttled_before = group.throttled()["nr_throttled"]
    busy = [_python(testbed, "edge-2", BUSY, 1.5) for _ in range(2)]
    try:
        for proc in busy:
            assert _next_json(proc) == {"ready": True}
        assert {p.pid for p in busy} <= set(group.pids())
        results = [_next_json(proc) for proc in busy]
    finally:
        _finish(*busy)
        testbed.cpu("edge-2", None)
    share = sum(r["cpu_s"] / r["wall_s"] for r in results)
    print(f"cpu cap 0.25 core: two busy loops got {share:.3f} core together")
    # An uncapped busy loop takes a whole core; two of them share the 0.25 cap.
    assert 0.12 <= share <= 0.30
    assert group.throttled()["nr_throttled"] > throttled_before
    assert testbed.cpu_fraction("edge-2") is None


def test_small_cpu_shares_lengthen_the_period_only_as_far_as_the_kernel_needs(
    testbed: Testbed,
) -> None:
    # Regression: quotas were set against the kernel's 100 ms default period, so a 0.02-core
    # robot ran 2 ms then stood still 98 ms and its frame times moved in 0.1 s steps. The kernel
    # refuses quotas under 1 ms: a small share gets exactly 1 ms in the shortest period it allows.
    group = testbed.cgroup("edge-2")
    if group is None:
        pytest.skip("no cgroup-v1 cpu controller mounted")
    try:
        for share, period_us in ((0.2, DEFAULT_CFS_PERIOD_US), (0.05, 20_000), (0.02, 50_000)):
            testbed.cpu("edge-2", share)
            assert group.bandwidth_us() == (MIN_QUOTA_US, period_us)
            assert testbed.cpu_fraction("edge-2") == share
        testbed.cpu("edge-2", 0.03)
        assert testbed.cpu_fraction("edge-2") == 0.03  # 1000 µs per 33334 µs, read back rounded
        with pytest.raises(UserError, match=r"cpu fraction 0.0005 is out of range: use 0.001"):
            testbed.cpu("edge-2", 0.0005)
    finally:
        testbed.cpu("edge-2", None)
    assert group.bandwidth_us() == (-1, DEFAULT_CFS_PERIOD_US)


def test_compose_robot_shaping_commands_work_in_a_host(testbed: Testbed) -> None:
    robot = yaml.safe_load(COMPOSE_FILE.read_text())["services"]["robot"]
    script = robot["command"][2]
    # As docker compose passes it ($$ escapes $), without the final exec of the daemon.
    setup = script.replace("$$", "$").rsplit("&&", 1)[0]
    env = {**os.environ, "ROBOT_UPLINK_MBIT": "3"}
    try:
        done = testbed.exec("robot", [SH, "-c", setup], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        assert testbed.link_rates("robot") == {"uplink_mbit": 3.0, "downlink_mbit": None}
    finally:
        testbed.shape("robot", None)
    assert testbed.link_rates("robot")["uplink_mbit"] is None


def test_compose_fleet_runs_in_the_testbed_with_data_bypassing_the_registry(
    testbed: Testbed,
) -> None:
    """The compose fleet file as is: hosts by name, peers meeting through the registry's router
    and then talking directly, so the registry's link carries almost nothing."""
    replies, reply_bytes = 10, 1 << 20
    router = _python(testbed, "registry", ZENOH_ROUTER, COMPOSE_FLEET)
    procs = [router]
    try:
        assert _next_json(router) == {"ready": True}
        server = _python(testbed, "edge-1", ZENOH_SERVER, COMPOSE_FLEET, "edge-1", reply_bytes)
        procs.append(server)
        assert _next_json(server) == {"ready": True}
        before = {h: testbed.counters(h) for h in ("registry", "robot")}
        client = _python(testbed, "robot", ZENOH_CLIENT, COMPOSE_FLEET, "robot-1", replies)
        procs.append(client)
        assert _next_json(client) == {"replies": replies}
        after = {h: testbed.counters(h) for h in ("registry", "robot")}
    finally:
        for proc in procs[:2]:
            if proc.poll() is None:
                proc.terminate()
        _finish(*reversed(procs))
    robot_rx = after["robot"]["rx_bytes"] - before["robot"]["rx_bytes"]
    registry_bytes = sum(
        after["registry"][k] - before["registry"][k] for k in ("rx_bytes", "tx_bytes")
    )
    print(f"compose fleet: robot received {robot_rx} B, registry link carried {registry_bytes} B")
    assert robot_rx >= replies * reply_bytes
    assert registry_bytes < 0.01 * robot_rx


def test_bad_input_is_one_clear_error(testbed: Testbed, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(TestbedError, match=r"unknown host 'nope'.*registry, robot, edge-1"):
        testbed.shape("nope", 1)
    with pytest.raises(UserError, match="uplink -1 Mbit/s is out of range"):
        testbed.shape("robot", -1)
    with pytest.raises(UserError, match="cpu fraction 0 is out of range"):
        testbed.cpu("robot", 0)
    with pytest.raises(TestbedError, match=f"testbed {testbed.name} already exists"):
        Testbed(testbed.name, hosts=["robot"]).up()

    app = typer.Typer()
    testbed_cli.register(app)
    runner = CliRunner()
    status = runner.invoke(app, ["testbed", "status", "--name", testbed.name, "--json"])
    assert status.exit_code == 0, status.output
    info = json.loads(status.stdout)
    assert {h: e["address"] for h, e in info["hosts"].items()} == testbed.addresses()
    bad = runner.invoke(app, ["testbed", "shape", "nope", "--uplink-mbit", "1", "-n", testbed.name])
    assert bad.exit_code == 2
    assert "unknown host 'nope'" in bad.output and "Traceback" not in bad.output
    missing = runner.invoke(app, ["testbed", "cpu", "robot", "--fraction", "0.5", "-n", "absent"])
    assert missing.exit_code == 2 and "testbed absent is not up" in missing.output
    echo = runner.invoke(
        app, ["testbed", "exec", "robot", "-n", testbed.name, "--", "sh", "-c", "exit 3"]
    )
    assert echo.exit_code == 3

    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    with pytest.raises(TestbedError, match="the testbed needs root"):
        Testbed(_name("x")).up()


def test_down_after_a_crash_leaves_nothing_behind() -> None:
    before = _root_snapshot()
    name = _name("d")
    tb = Testbed(name, hosts=HOSTS)
    tb.up()
    try:
        tb.shape("robot", 2, 3)
        cgroup = tb.cgroup("robot")
        if cgroup is not None:
            tb.cpu("robot", 0.5)
        sleeper = tb.popen("robot", ["sleep", "30"])
        stubborn = _python(tb, "edge-1", STUBBORN)  # ignores SIGTERM: needs SIGKILL
        assert next(_lines(stubborn)).strip() == "ready"
        # A crashed owner: the state file is gone and a fresh object knows only the name.
        tb.state_file.unlink()
    except BaseException:
        tb.down()
        raise
    removed = Testbed(name).down()
    assert sleeper.wait(timeout=1) != 0
    assert stubborn.wait(timeout=1) == -9
    assert stubborn.stdout is not None
    stubborn.stdout.close()
    assert f"process {sleeper.pid}" in removed and f"process {stubborn.pid}" in removed

    assert not [n for n in os.listdir(NETNS_DIR) if n.startswith(f"{name}.")]
    assert not (ETC_NETNS_DIR.is_dir() and list(ETC_NETNS_DIR.glob(f"{name}.*")))
    mount = find_cpu_mount()
    if mount is not None:
        assert not (mount / "elasticfog" / name).exists()
    assert not tb.state_file.exists()
    # Nothing was ever made in the root namespace, and nothing is left there.
    assert _root_snapshot() == before
    assert Testbed(name).down() == []  # idempotent
    assert not Path(f"/proc/{sleeper.pid}").exists()
