"""Prometheus metrics of a running fleet, scraped over HTTP on loopback (docs/metrics.md).

Registry, two cloud daemons and a robot run as real subprocesses, each serving `/metrics` on a
port of its machine's `metrics` section; the serving deployment is SIGKILLed mid-run. The text
each serves is parsed with prometheus_client's own parser, and the counters must agree with what
the robot wrote in its telemetry file (the records its run summary counts): frames by action,
fallbacks by reason, bytes sent, the latency histogram's count; the registry counts the one
failover; every name docs/metrics.md lists is served by the daemon it names.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import urllib.request
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from deploy.demo import METRICS_DAEMONS, answered_by, read_telemetry
from deploy.demo import ROBOT_ID as DEMO_ROBOT
from deploy.procs import elasticfog_argv, free_tcp_port
from deploy.readiness import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

ROBOT = "robot-1"
WAIT_S = 30.0
SCRAPE_TIMEOUT_S = 2.0
SLOW_FPS = 4.0
"""Frames a quarter of a second apart: between two, the robot's counters are still and a scrape
sees the same frames as its telemetry file."""
QUIET_TRIES = 40
"""Bound of the tries for a scrape between two frames (each waits for the next frame)."""
DEMO_FRAMES = 30
DEMO_KILL_AT = 10
DEMO_START_S = 60.0
"""Bound of the demo's start (model split, four daemons) and of its run after the scrape."""
MAX_PORT = 65535
DOCS = Path(__file__).resolve().parents[2] / "docs" / "metrics.md"

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def scrape(url: str) -> Samples:
    """Every sample `url` serves: (sample name, labels) -> value, parsed as Prometheus does."""
    with urllib.request.urlopen(url, timeout=SCRAPE_TIMEOUT_S) as response:
        assert response.headers.get_content_type() == "text/plain"
        text = response.read().decode("utf-8")
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def total(samples: Samples, name: str, **labels: str) -> float:
    """The sum of `name`'s samples whose labels include `labels`."""
    want = set(labels.items())
    return sum(v for (n, ls), v in samples.items() if n == name and want <= ls)


def by_label(samples: Samples, name: str, label: str) -> dict[str, float]:
    out: Counter[str] = Counter()
    for (n, ls), v in samples.items():
        if n == name:
            out[dict(ls)[label]] += v
    return {k: v for k, v in out.items() if v}


def documented_names() -> dict[str, list[str]]:
    """daemon -> the metric names docs/metrics.md lists under its heading."""
    names: dict[str, list[str]] = {}
    daemon = None
    for line in DOCS.read_text(encoding="utf-8").splitlines():
        heading = re.match(r"^## (registry|cloud|robot)\b", line, re.IGNORECASE)
        if heading:
            daemon = heading.group(1).lower()
            continue
        row = re.match(r"^\| `(elasticfog_[a-z_]+)`", line)
        if row and daemon:
            names.setdefault(daemon, []).append(row.group(1))
    return names


def _metrics(port: int) -> dict[str, Any]:
    return {"metrics": {"port": port, "host": "127.0.0.1"}}


def test_counters_of_a_running_fleet_agree_with_its_telemetry(
    make_fleet, local_fleet, tmp_path: Path
) -> None:
    ports = {name: free_tcp_port() for name in ("registry", "edge-1", "edge-2", ROBOT)}
    fleet = make_fleet(
        registry=_metrics(ports["registry"]),
        machines={
            "edge-1": _metrics(ports["edge-1"]),
            "edge-2": _metrics(ports["edge-2"]),
            ROBOT: {**_metrics(ports[ROBOT]), "fps": SLOW_FPS},
        },
    )
    url = {name: f"http://127.0.0.1:{port}/metrics" for name, port in ports.items()}
    lf = local_fleet(fleet)
    lf.start_registry()
    lf.start_clouds(["edge-1", "edge-2"])
    tap = lf.tap(ROBOT)
    telemetry = tmp_path / "robot-1.jsonl"
    robot = lf.start_robot(ROBOT, "--policy", "cloud", telemetry=telemetry)
    first = tap.wait_for(
        lambda r: answered_by(r) is not None,
        timeout_s=WAIT_S,
        what="a frame answered by a deployment",
        procs=[robot],
    )
    serving = answered_by(first)
    other = "edge-2" if serving == "edge-1" else "edge-1"
    tap.wait_frame(int(first["frame"]) + 3, timeout_s=WAIT_S, procs=[robot])
    killed_at = lf.kill(serving)
    took_over = tap.wait_for(
        lambda r: r["at"] >= killed_at and answered_by(r) == other,
        timeout_s=WAIT_S,
        what=f"a frame answered by {other} after {serving} was killed",
        procs=[robot],
    )
    tap.wait_frame(int(took_over["frame"]) + 3, timeout_s=WAIT_S, procs=[robot])

    # A scrape between two frames: the same frames before and after it, and in the file.
    for _ in range(QUIET_TRIES):
        before = scrape(url[ROBOT])
        records = read_telemetry(telemetry)
        after = scrape(url[ROBOT])
        frames = total(before, "elasticfog_robot_frames_total")
        if frames == total(after, "elasticfog_robot_frames_total") == len(records):
            break
        n = len(records)
        tap.wait_frame(n, timeout_s=WAIT_S, procs=[robot])
    else:
        pytest.fail(f"no scrape between two frames in {QUIET_TRIES} tries")
    robot_samples = before

    actions = Counter(r["action"] for r in records)
    assert by_label(robot_samples, "elasticfog_robot_frames_total", "action") == actions
    served = Counter(r["served_by"] for r in records)
    assert by_label(robot_samples, "elasticfog_robot_frames_total", "served_by") == served
    reasons = Counter(r["reason"] for r in records if r["fallback"])
    assert by_label(robot_samples, "elasticfog_robot_fallbacks_total", "reason") == reasons
    answered = Counter(answered_by(r) for r in records if answered_by(r) is not None)
    by_dep = by_label(robot_samples, "elasticfog_robot_answered_frames_total", "deployment")
    assert by_dep == answered
    assert total(robot_samples, "elasticfog_robot_sent_bytes_total") == sum(
        r["bytes_up"] for r in records
    )
    assert total(robot_samples, "elasticfog_robot_frame_latency_seconds_count") == len(records)
    assert total(robot_samples, "elasticfog_robot_frame_latency_seconds_sum") == pytest.approx(
        sum(r["latency_s"] for r in records), rel=1e-3
    )

    # The registry counted the one failover; the robot holds the route the registry gave it.
    registry = scrape(url["registry"])
    assert total(registry, "elasticfog_registry_failovers_total") == 1
    assert total(registry, "elasticfog_registry_route_changes_total", reason="deployment_lost") == 1
    assert total(registry, "elasticfog_registry_deployments_alive") == 1
    assert total(registry, "elasticfog_registry_robots_alive") == 1
    assert total(registry, "elasticfog_registry_routed_robots", deployment=other) == 1
    assert total(registry, "elasticfog_registry_round_duration_seconds_count") > 0
    route = lf.route(ROBOT)
    assert route is not None and route.deployment == other
    assert total(robot_samples, "elasticfog_robot_route_epoch") == route.epoch
    assert total(robot_samples, "elasticfog_robot_route_info", deployment=other) == 1

    # The deployment that took over answered at least what the robot took from it (a reply
    # that came after the robot's deadline is `ok` there and a fallback here).
    cloud = scrape(url[other])
    ok = total(cloud, "elasticfog_cloud_inference_requests_total", robot=ROBOT, outcome="ok")
    assert ok >= answered[other] > 0
    assert total(cloud, "elasticfog_cloud_robot_state", robot=ROBOT, state="service") == 1
    assert total(cloud, "elasticfog_cloud_inference_queue_duration_seconds_count") == ok
    assert total(cloud, "elasticfog_cloud_capacity_requests") > 0

    # Every documented name is served by its daemon (histograms as their _count).
    served_names = {
        "robot": {n for n, _ in robot_samples},
        "registry": {n for n, _ in registry},
        "cloud": {n for n, _ in cloud},
    }
    documented = documented_names()
    assert set(documented) == {"robot", "cloud", "registry"}
    for daemon, names in documented.items():
        missing = [n for n in names if not _served(n, served_names[daemon])]
        assert not missing, f"{daemon}: documented but not served: {missing}"

    result = robot.stop()
    assert not result.killed and result.returncode == 0, robot.log_tail()
    # Once stopped, nothing answers on its port any more.
    wait_until(
        lambda: _refused(url[ROBOT]), timeout_s=WAIT_S, what="the robot's metrics port to close"
    )


def _refused(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=SCRAPE_TIMEOUT_S):
            pass
    except OSError:
        return True
    return False


def _free_run(length: int, tries: int = 50) -> int:
    """The first of `length` consecutive TCP ports free on loopback right now."""
    import socket

    for _ in range(tries):
        base = free_tcp_port()
        if base + length - 1 > MAX_PORT:
            continue
        socks = []
        try:
            for port in range(base, base + length):
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(sock)
                sock.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for sock in socks:
                sock.close()
    raise AssertionError(f"no {length} consecutive free ports in {tries} tries")


def test_demo_metrics_serves_every_documented_name_on_each_daemon(
    demo_model: str, tmp_path: Path
) -> None:
    """`elasticfog demo --metrics-port-base P`: while it runs, each of its four daemons answers
    on its port with the names docs/metrics.md lists for it; the summary lists the URLs, and
    the registry counts the failover the demo's summary reports."""
    base = _free_run(len(METRICS_DAEMONS))
    argv = [*elasticfog_argv(), "demo", "--frames", str(DEMO_FRAMES), "--fps", str(SLOW_FPS)]
    argv += ["--policy", "cloud", "--metrics-port-base", str(base), "--json"]
    argv += ["--kill-service-at", str(DEMO_KILL_AT)]
    work = tmp_path / "tmp"
    work.mkdir()
    demo = subprocess.Popen(
        argv,
        env=dict(os.environ, TMPDIR=str(work)),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    urls = {name: f"http://127.0.0.1:{base + i}/metrics" for i, name in enumerate(METRICS_DAEMONS)}
    try:
        wait_until(
            lambda: _frames_served(urls[DEMO_ROBOT]) > 0,
            timeout_s=DEMO_START_S,
            what="the demo robot's first frame on its /metrics",
        )
        scraped = {name: scrape(url) for name, url in urls.items()}
        # The demo kills the serving deployment at DEMO_KILL_AT: the registry counts it.
        wait_until(
            lambda: total(scrape(urls["registry"]), "elasticfog_registry_failovers_total") >= 1,
            timeout_s=DEMO_START_S,
            what="the registry's failover counter",
        )
        failovers = total(scrape(urls["registry"]), "elasticfog_registry_failovers_total")
        out, err = demo.communicate(timeout=DEMO_START_S)
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGINT)
            demo.wait(timeout=DEMO_START_S)
    assert demo.returncode == 0, err[-3000:]
    summary = json.loads(out)
    assert summary["metrics"] == urls
    assert failovers == len(summary["failovers"]) == 1, summary["failovers"]
    documented = documented_names()
    for name, samples in scraped.items():
        daemon = "cloud" if name.startswith("edge") else name.split("-")[0]
        served = {n for n, _ in samples}
        missing = [n for n in documented[daemon] if not _served(n, served)]
        if name != "edge-1":  # the standby: a robot's requests are counted from its first
            missing = [n for n in missing if n != "elasticfog_cloud_inference_requests_total"]
        assert not missing, f"{name}: documented but not served: {missing}"


def _served(name: str, served: set[str]) -> bool:
    return bool({name, f"{name}_total", f"{name}_count", f"{name}_info"} & served)


def _frames_served(url: str) -> float:
    try:
        return total(scrape(url), "elasticfog_robot_frames_total")
    except OSError:
        return 0.0


@pytest.fixture(scope="module")
def demo_model(e2e_cache: Path) -> str:
    """The demo's model split into the test cache once."""
    from common.init_cli import DEFAULT_MODEL
    from common.partition import load_partition

    load_partition(DEFAULT_MODEL)
    return DEFAULT_MODEL
