"""Integration fixtures: free loopback ports and real Zenoh sessions built by `common.session`
(multicast scouting off, loopback only), plus waits on real events instead of sleeps.

- `free_port`: a TCP port on 127.0.0.1 that was free a moment ago; `free_port_factory()` gives
  several distinct ones.
- `zenoh_router`: a router session (what the registry embeds) on a free port, with its endpoint.
- `open_peer(**kwargs)`: peer sessions connected to that router and listening on loopback
  (gossip makes them connect to each other directly), all closed at teardown.
- `wait_for_token(session, key)`, `wait_for_token_gone(session, key)`, `wait_for_peer(session,
  zid)`: block until the event happens, or fail after a timeout with a message naming it.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from cloudd.daemon import CloudDaemon
from common.config import FleetConfig
from common.session import open_session

LOOPBACK = "127.0.0.1"
WAIT_TIMEOUT_S = 10.0
LEASE_MS = 1000


def find_free_port() -> int:
    """A TCP port on the loopback interface that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((LOOPBACK, 0))
        port: int = sock.getsockname()[1]
        return port


def loopback_endpoint(port: int) -> str:
    """`tcp/127.0.0.1:<port>`."""
    return f"tcp/{LOOPBACK}:{port}"


@contextlib.contextmanager
def running_cloud(cfg: FleetConfig, deployment: str, wait_s: float) -> Iterator[CloudDaemon]:
    """A CloudDaemon whose `run()` runs in a thread, ready (else the test fails), stopped and
    joined on exit."""
    cloud = CloudDaemon(cfg, deployment)
    thread = threading.Thread(target=cloud.run, name=f"cloud-{deployment}", daemon=True)
    thread.start()
    try:
        if not cloud.ready.wait(wait_s):
            pytest.fail(f"{deployment} did not become ready within {wait_s} s")
        yield cloud
    finally:
        cloud.stop()
        thread.join(wait_s)
    assert not thread.is_alive(), "the cloud daemon did not stop"


@pytest.fixture
def free_port() -> int:
    """A free loopback TCP port."""
    return find_free_port()


@pytest.fixture
def free_port_factory() -> Callable[[], int]:
    """Call it for as many distinct free loopback ports as a test needs."""
    given: set[int] = set()

    def next_port() -> int:
        for _ in range(100):
            port = find_free_port()
            if port not in given:
                given.add(port)
                return port
        raise RuntimeError("no new free port after 100 tries")

    return next_port


@dataclass
class Router:
    """A running router session and where to reach it."""

    session: zenoh.Session
    endpoint: str
    port: int


@pytest.fixture
def zenoh_router(free_port: int) -> Iterator[Router]:
    """A Zenoh router on a free loopback port, closed at teardown."""
    endpoint = loopback_endpoint(free_port)
    session = open_session(router=True, listen=[endpoint], lease_ms=LEASE_MS)
    try:
        yield Router(session=session, endpoint=endpoint, port=free_port)
    finally:
        session.close()


@pytest.fixture
def open_peer(zenoh_router: Router) -> Iterator[Callable[..., zenoh.Session]]:
    """Factory of peer sessions connected to `zenoh_router`, listening on loopback (any port);
    keyword arguments go to `open_session` and override these defaults."""
    sessions: list[zenoh.Session] = []

    def make(**kwargs: Any) -> zenoh.Session:
        options: dict[str, Any] = {
            "mode": "peer",
            "connect": [zenoh_router.endpoint],
            "listen": [f"tcp/{LOOPBACK}:0"],
            "lease_ms": LEASE_MS,
        }
        options.update(kwargs)
        session = open_session(**options)
        sessions.append(session)
        return session

    try:
        yield make
    finally:
        for session in reversed(sessions):
            session.close()


@pytest.fixture
def zenoh_peer(open_peer: Callable[..., zenoh.Session]) -> zenoh.Session:
    """One peer connected to `zenoh_router`."""
    return open_peer()


def _wait_liveliness(
    session: zenoh.Session, key: str, kind: zenoh.SampleKind, timeout_s: float
) -> None:
    seen = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        if sample.kind == kind and str(sample.key_expr) == key:
            seen.set()

    # history=True reports tokens already alive, so a PUT that happened earlier is not missed.
    subscriber = session.liveliness().declare_subscriber(key, on_sample, history=True)
    try:
        if kind == zenoh.SampleKind.DELETE and not _token_alive(session, key, timeout_s):
            return
        if not seen.wait(timeout_s):
            state = "appear" if kind == zenoh.SampleKind.PUT else "disappear"
            pytest.fail(f"liveliness token {key} did not {state} within {timeout_s} s")
    finally:
        subscriber.undeclare()


def _token_alive(session: zenoh.Session, key: str, timeout_s: float) -> bool:
    replies = session.liveliness().get(key, timeout=timeout_s)
    return any(reply.ok is not None for reply in replies)


@pytest.fixture
def wait_for_token() -> Callable[..., None]:
    """`wait_for_token(session, key, timeout_s=10)`: block until the liveliness token `key` is
    alive as seen from `session`."""

    def wait(session: zenoh.Session, key: str, timeout_s: float = WAIT_TIMEOUT_S) -> None:
        _wait_liveliness(session, key, zenoh.SampleKind.PUT, timeout_s)

    return wait


@pytest.fixture
def wait_for_token_gone() -> Callable[..., None]:
    """`wait_for_token_gone(session, key, timeout_s=10)`: block until the token `key` is gone."""

    def wait(session: zenoh.Session, key: str, timeout_s: float = WAIT_TIMEOUT_S) -> None:
        _wait_liveliness(session, key, zenoh.SampleKind.DELETE, timeout_s)

    return wait


@pytest.fixture
def wait_for_peer() -> Callable[..., None]:
    """`wait_for_peer(session, zid, timeout_s=10)`: block until `session` has a direct transport
    to the node `zid` (e.g. two peers linked by gossip)."""

    def wait(session: zenoh.Session, zid: Any, timeout_s: float = WAIT_TIMEOUT_S) -> None:
        linked = threading.Event()
        wanted = str(zid)

        def on_event(event: Any) -> None:
            if event.kind == zenoh.SampleKind.PUT and str(event.transport.zid) == wanted:
                linked.set()

        listener = session.info.declare_transport_events_listener(on_event, history=True)
        try:
            if not linked.wait(timeout_s):
                pytest.fail(f"no direct transport to {wanted} within {timeout_s} s")
        finally:
            listener.undeclare()

    return wait
