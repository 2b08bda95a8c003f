"""Fixtures of the e2e tier: real daemons as subprocesses, on loopback, with their logs on failure.

Each test gets a fleet of its own (`make_fleet`: `elasticfog init`'s file, a free registry port,
a unique fleet name, a small model input so frames are cheap on two cores) and a `LocalFleet`
that starts the daemons with the real CLI in their own process groups and stops them with SIGINT,
then SIGKILL, whatever happens. When a test fails, the tail of every daemon's log is attached to
its report. Tests using `e2e_watchdog` are bounded in time (SIGALRM), so a hung daemon fails one
test instead of the run.
"""

from __future__ import annotations

import os
import signal
import uuid
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import psutil
import pytest
import yaml

from deploy.local_fleet import LocalFleet, merge_into, write_local_fleet
from deploy.testbed import ETC_NETNS_DIR, NETNS_DIR

E2E_TEST_TIMEOUT_S = 90
"""Wall-clock bound of one e2e test, startup and teardown of its daemons included."""

TEST_INPUT_SHAPE = [3, 64, 64]
"""Small frames: the runtime is what is under test, not the model's speed."""

TEST_MODEL = "zoo:vgg"


def remains_of_testbed(name: str) -> list[str]:
    """Whatever of testbed `name` still exists: namespaces, netns config, cgroups."""
    left = (
        [f"netns {n}" for n in os.listdir(NETNS_DIR) if n.startswith(f"{name}.")]
        if NETNS_DIR.is_dir()
        else []
    )
    if ETC_NETNS_DIR.is_dir():
        left += [f"etc {p}" for p in ETC_NETNS_DIR.glob(f"{name}.*")]
    left += [f"cgroup {p}" for p in Path("/sys/fs/cgroup").glob(f"*/elasticfog/{name}")]
    return left


def processes_under(workdir: Path) -> list[str]:
    """Processes whose command line names a file under `workdir` (our daemons, the observer)."""
    found = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        cmdline = proc.info.get("cmdline") or []
        if any(str(workdir) in part for part in cmdline):
            found.append(f"process {proc.info['pid']}: {' '.join(cmdline)[:120]}")
    return found


# Settings the tests rely on (seconds): a deadline far above a frame's cost on this input, a
# bound that an injected delay of INJECT_DELAY_MS breaks but the deadline does not, and a short
# hysteresis so a switch happens within a test.
TEST_DEADLINE_S = 0.6
TEST_BOUND_S = 0.12
TEST_WINDOW = 8
TEST_HYSTERESIS_S = 0.5
TEST_FPS = 20.0


@dataclass
class Fleet:
    """A fleet.yaml written for one test."""

    dir: Path
    config: Path
    name: str
    data: dict[str, Any]

    @property
    def endpoint(self) -> str:
        return str(self.data["registry"]["endpoint"])


def write_test_fleet(directory: Path, **changes: Any) -> Fleet:
    """A fleet.yaml with the test settings above; `changes` are merged into the YAML mapping
    (nested mappings merge, other values replace)."""
    settings: dict[str, Any] = {
        "input_shape": TEST_INPUT_SHAPE,
        "deadline_s": TEST_DEADLINE_S,
        "latency_bound": {
            "stat": "median",
            "seconds": TEST_BOUND_S,
            "window": TEST_WINDOW,
            "hysteresis_s": TEST_HYSTERESIS_S,
        },
        "machines": {"robot-1": {"fps": TEST_FPS}},
    }
    name = f"e2e-{uuid.uuid4().hex[:8]}"
    path = write_local_fleet(
        directory, fleet=name, model=TEST_MODEL, changes=merge_into(settings, changes)
    )
    data = yaml.safe_load(path.read_text())
    return Fleet(dir=directory, config=path, name=name, data=data)


@pytest.fixture(scope="session")
def e2e_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One model cache for the whole e2e run, shared with the daemons through the environment,
    and the test model split into it once (daemons then load it; none exports it)."""
    from common.models import CACHE_DIR_ENV

    previous = os.environ.get(CACHE_DIR_ENV)
    if previous is None:
        os.environ[CACHE_DIR_ENV] = str(tmp_path_factory.mktemp("cache"))
    try:
        from common.partition import load_partition

        load_partition(TEST_MODEL, input_shape=tuple(TEST_INPUT_SHAPE))
        yield Path(os.environ[CACHE_DIR_ENV])
    finally:
        if previous is None:
            os.environ.pop(CACHE_DIR_ENV, None)


@pytest.fixture
def make_fleet(tmp_path: Path, e2e_cache: Path) -> Callable[..., Fleet]:
    """`make_fleet(**changes)` -> a fleet.yaml in this test's tmp dir."""

    def make(**changes: Any) -> Fleet:
        return write_test_fleet(tmp_path, **changes)

    return make


@pytest.fixture
def local_fleet(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Callable[..., Any]]:
    """`local_fleet(fleet, **options)` -> a LocalFleet for it (`options`: LocalFleet's, e.g.
    `argv0`); every daemon it starts is stopped at teardown and the daemons' logs are attached to
    the report of a failing test. A daemon that logged a traceback fails the test at teardown:
    whatever a test does to them (kills, bad input, lost peers), daemons report problems in a
    line, never as a crash."""
    opened: list[LocalFleet] = []

    def open_fleet(fleet: Fleet, **options: Any) -> LocalFleet:
        lf = LocalFleet(
            fleet.config, tmp_path / f"run{len(opened)}", startup_timeout_s=45.0, **options
        )
        lf.__enter__()
        opened.append(lf)
        return lf

    request.node._ef_fleets = opened  # read by pytest_runtest_makereport below
    try:
        yield open_fleet
    finally:
        for lf in reversed(opened):
            lf.close()
    crashed = [p.name for lf in opened for p in lf.procs.procs if "Traceback" in p.log_text()]
    assert not crashed, f"traceback in the log of {', '.join(crashed)}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, Any, None]:
    outcome = yield
    report = outcome.get_result()
    fleets = getattr(item, "_ef_fleets", None)
    if report.failed and fleets:
        for lf in fleets:
            report.sections.append((f"daemon logs ({lf.workdir})", lf.procs.format_logs()))


class E2ETimeout(Exception):
    """An e2e test ran past E2E_TEST_TIMEOUT_S."""


@pytest.fixture
def e2e_watchdog() -> Iterator[None]:
    """Fail a test that runs too long (the fixtures' teardown still stops its daemons). Test
    modules opt in with `pytestmark = [..., pytest.mark.usefixtures("e2e_watchdog")]`."""

    def expired(sig: int, frame: FrameType | None) -> None:
        raise E2ETimeout(f"e2e test exceeded {E2E_TEST_TIMEOUT_S} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, E2E_TEST_TIMEOUT_S)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="session")
def sdk_messages(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The .msg files zenoh-ros2-sdk reads (`tests.e2e.ros2_sdk`), registered with it once."""
    from tests.e2e.ros2_sdk import write_messages

    return write_messages(tmp_path_factory.mktemp("msgs"))


@pytest.fixture
def sdk_peer(sdk_messages: Path) -> Iterator[Callable[[int], Any]]:
    """`sdk_peer(port)` -> zenoh-ros2-sdk's peer on the router at `port`, closed at teardown."""
    from tests.e2e.ros2_sdk import SdkPeer

    peers: list[SdkPeer] = []

    def make(port: int) -> SdkPeer:
        peers.append(SdkPeer(port))
        return peers[-1]

    try:
        yield make
    finally:
        for peer in peers:
            peer.close()
