"""common.daemon: the lifecycle owns what startup declared, and callbacks never raise into Zenoh.

Fake resources record when they are released, so the order is checked without a network: a
startup that fails half-way still releases what it had declared (regression: the daemons each
wrapped startup in their own try/except for this), the liveliness token goes first whatever its
place in startup, a release that fails does not keep the others, and `guarded` callbacks survive
errors with their log lines throttled.
"""

from __future__ import annotations

import logging
import signal
from typing import Any

import pytest

from common.daemon import Daemon
from common.throttled_log import ThrottledLog
from common.wire import WireError

LOGGER = "tests.unit.test_daemon"


class Resource:
    """A context manager that records its release in `released`."""

    def __init__(self, name: str, released: list[str], *, fail: bool = False) -> None:
        self.name = name
        self.released = released
        self.fail = fail
        self.entered = False

    def __enter__(self) -> Resource:
        self.entered = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.released.append(self.name)
        if self.fail:
            raise RuntimeError(f"{self.name} cannot be released")


class FailingStartup(Daemon):
    """Declares a session, a subscriber, a thread, announces its token, declares a queryable,
    then fails."""

    name = "test"

    def __init__(self) -> None:
        super().__init__()
        self.released: list[str] = []

    def startup(self) -> None:
        self.hold(Resource("session", self.released), "session")
        self.hold(Resource("subscriber", self.released), "subscriber")
        self.on_release(self._join, "thread", what="thread", timeout_s=1.0)
        self.announce(Resource("token", self.released))  # type: ignore[arg-type]
        self.hold(Resource("queryable", self.released), "queryable")
        raise RuntimeError("startup failed half-way")

    def main_loop(self) -> None:
        raise AssertionError("the main loop must not run after a failed startup")

    def _join(self, name: str, *, timeout_s: float) -> None:
        self.released.append(name)


def test_shutdown_after_a_failing_startup_releases_what_was_declared_token_first() -> None:
    daemon = FailingStartup()
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(RuntimeError, match="half-way"):
        daemon.run()
    assert daemon.released == ["token", "queryable", "thread", "subscriber", "session"]
    assert daemon.closing.is_set()
    assert signal.getsignal(signal.SIGINT) is before, "the previous handler is restored"


def test_a_release_that_fails_is_logged_and_the_rest_still_run(
    caplog: pytest.LogCaptureFixture,
) -> None:
    daemon = Daemon()
    released: list[str] = []
    daemon.hold(Resource("session", released), "session")
    daemon.hold(Resource("publisher", released, fail=True), "publisher")
    daemon.announce(Resource("token", released, fail=True))  # type: ignore[arg-type]
    daemon.shutdown()
    assert released == ["token", "publisher", "session"]
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("releasing the publisher failed" in line for line in lines), lines
    assert any("releasing the liveliness token failed" in line for line in lines), lines


def test_shutdown_twice_releases_once() -> None:
    daemon = Daemon()
    released: list[str] = []
    resource = daemon.hold(Resource("file", released), "file")
    assert resource.entered, "hold enters the context manager and returns what it entered as"
    daemon.shutdown()
    daemon.shutdown()
    assert released == ["file"]


def test_a_clean_run_releases_everything_after_the_main_loop() -> None:
    released: list[str] = []

    class Quick(Daemon):
        def startup(self) -> None:
            self.hold(Resource("session", released), "session")
            self.announce(Resource("token", released))  # type: ignore[arg-type]

        def main_loop(self) -> None:
            released.append("main loop")

    assert Quick().run() == 0
    assert released == ["main loop", "token", "session"]


# -- guarded callbacks ----------------------------------------------------------------------------
def _daemon(burst: int = 3) -> Daemon:
    daemon = Daemon()
    daemon.name = "test"
    daemon.throttled = ThrottledLog(
        logging.getLogger(LOGGER), label=lambda: daemon.name, burst=burst, window_s=3600.0
    )
    return daemon


def test_a_guarded_callback_survives_an_exception_and_logs_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    daemon = _daemon()
    seen: list[tuple[int, str]] = []

    def callback(n: int) -> None:
        raise KeyError(n)

    guarded = daemon.guarded(callback, on_error=lambda n, exc: seen.append((n, type(exc).__name__)))
    guarded(7)  # does not raise
    assert seen == [(7, "KeyError")]
    [record] = [r for r in caplog.records if r.name == LOGGER]
    assert record.levelno == logging.ERROR and record.exc_info
    assert record.filename == "daemon.py", "the record names the caller, not the throttle"
    assert "unexpected error in callback" in record.getMessage()


def test_bad_input_in_a_guarded_callback_is_one_warning_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    daemon = _daemon()

    def on_sample(payload: bytes) -> None:
        raise WireError(f"not a message: {payload!r}")

    daemon.guarded(on_sample, what="tele/robot-1")(b"\xc1")
    [record] = [r for r in caplog.records if r.name == LOGGER]
    assert record.levelno == logging.WARNING and not record.exc_info
    assert record.getMessage() == "test: bad input on tele/robot-1: not a message: b'\\xc1'"


def test_guarded_logs_are_throttled(caplog: pytest.LogCaptureFixture) -> None:
    daemon = _daemon(burst=3)
    calls: list[int] = []

    def callback(n: int) -> None:
        calls.append(n)
        raise ValueError("boom")

    guarded = daemon.guarded(callback)
    for n in range(20):
        guarded(n)
    assert calls == list(range(20)), "every call still runs"
    assert len([r for r in caplog.records if r.name == LOGGER]) == 3


def test_errors_while_closing_are_quiet_and_drop_when_closing_skips(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    daemon = _daemon()
    calls: list[Any] = []

    def callback(arg: Any) -> None:
        calls.append(arg)
        raise RuntimeError("the session is gone")

    daemon.shutdown()
    daemon.guarded(callback)(1)
    daemon.guarded(callback, drop_when_closing=True)(2)
    assert calls == [1]
    assert not [r for r in caplog.records if r.levelno >= logging.INFO]


# -- the throttled log ----------------------------------------------------------------------------
def test_throttled_log_counts_what_it_suppressed_when_the_next_window_opens(
    caplog: pytest.LogCaptureFixture,
) -> None:
    now = [0.0]
    throttled = ThrottledLog(
        logging.getLogger(LOGGER),
        label=lambda: "edge-1",
        burst=2,
        window_s=10.0,
        clock=lambda: now[0],
    )
    results = [throttled.warning("bad request %d", n) for n in range(5)]
    assert results == [True, True, False, False, False]
    now[0] = 11.0
    assert throttled.warning("bad request %d", 5)
    assert [r.getMessage() for r in caplog.records if r.name == LOGGER] == [
        "bad request 0",
        "bad request 1",
        "edge-1: 3 more warnings were not logged in the last 10 s",
        "bad request 5",
    ]


class Recording(Daemon):
    """Records whether `ready` was set when startup ran and when the main loop ran."""

    name = "recording"

    def __init__(self) -> None:
        super().__init__()
        self.seen: dict[str, bool] = {}

    def startup(self) -> None:
        self.seen["startup"] = self.ready.is_set()

    def main_loop(self) -> None:
        self.seen["main_loop"] = self.ready.is_set()


def test_ready_is_set_between_startup_and_the_main_loop_and_cleared_by_shutdown() -> None:
    daemon = Recording()
    assert daemon.run() == 0
    assert daemon.seen == {"startup": False, "main_loop": True}
    assert not daemon.ready.is_set()
    failing = FailingStartup()
    with pytest.raises(RuntimeError):
        failing.run()
    assert not failing.ready.is_set()  # a startup that failed never says ready
