"""Fixtures for every test tier.

- `isolated_cache` (autouse, whole session): ``ELASTICFOG_CACHE_DIR`` points at a fresh temporary
  directory, so tests never read or fill the user's model cache, and daemons started as
  subprocesses inherit the same cache.
- `_note_threads_left_behind` (autouse): non-daemon threads a test leaves running are named at
  the end of the run, which then exits with its status instead of waiting for them.
- `pytest_configure`: a run started in the background by a script (`bash .ci/run &`) inherits
  SIGINT ignored, as POSIX shells start background jobs, and so would every command a test
  interrupts (`demo`, `bench`): Ctrl-C tests would wait on commands that never see it. The run
  takes Python's own SIGINT handler back, as a run in the foreground has it.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

CACHE_DIR_ENV = "ELASTICFOG_CACHE_DIR"


def pytest_configure(config: pytest.Config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session", autouse=True)
def isolated_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A per-session model cache directory, set in the environment for the whole run."""
    previous = os.environ.get(CACHE_DIR_ENV)
    path = tmp_path_factory.mktemp("elasticfog-cache")
    os.environ[CACHE_DIR_ENV] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop(CACHE_DIR_ENV, None)
        else:
            os.environ[CACHE_DIR_ENV] = previous


# -- threads a test leaves behind ----------------------------------------------------------------
# A Zenoh callback runs on a non-daemon thread of its own ("... (pyo3-closure)") until its
# subscriber, queryable or session is closed, and the interpreter waits for every non-daemon
# thread at exit: a session a test (or a peer library's process-wide session) leaves open would
# hold the whole run at its end after the summary. Each test's new non-daemon threads that
# outlive it are noted with the test's id; at the end those still alive are named and the run
# exits with its own status instead of hanging.
_LEFT_BEHIND: dict[int, str] = {}
LEFT_THREAD_GRACE_S = 5.0


@pytest.fixture(autouse=True)
def _note_threads_left_behind(request: pytest.FixtureRequest) -> Iterator[None]:
    before = {t.ident for t in threading.enumerate()}
    yield
    for thread in threading.enumerate():
        if not thread.daemon and thread.ident not in before and thread.ident is not None:
            _LEFT_BEHIND.setdefault(thread.ident, request.node.nodeid)


def pytest_unconfigure(config: pytest.Config) -> None:
    deadline = time.monotonic() + LEFT_THREAD_GRACE_S
    main = threading.main_thread()
    alive = [t for t in threading.enumerate() if t is not main and not t.daemon]
    while alive and time.monotonic() < deadline:  # bounded: threads closing on their own
        alive[0].join(timeout=max(0.0, deadline - time.monotonic()))
        alive = [t for t in alive if t.is_alive()]
    if not alive:
        return
    where = [f"  {t.name}, from {_LEFT_BEHIND.get(t.ident or 0, 'outside a test')}" for t in alive]
    sys.stderr.write("threads left running at the end of the run:\n" + "\n".join(where) + "\n")
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(getattr(config, "_left_behind_status", 0))


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    session.config._left_behind_status = int(exitstatus)  # type: ignore[attr-defined]
