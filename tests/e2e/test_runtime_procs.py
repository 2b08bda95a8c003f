"""deploy.procs on plain Python subprocesses: what the e2e tests, the demo and the benchmarks rely
on to never leave a process behind."""

from __future__ import annotations

import os
import signal
import sys
import textwrap
from pathlib import Path

import psutil
import pytest

from deploy.procs import DaemonError, ProcessSet
from deploy.readiness import wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.usefixtures("e2e_watchdog")]

PY = [sys.executable, "-c"]

# Prints "ready" once its SIGINT handler is installed, then waits; exits 0 on SIGINT.
POLITE = textwrap.dedent(
    """
    import signal, sys, threading
    done = threading.Event()
    signal.signal(signal.SIGINT, lambda *a: done.set())
    print("ready", flush=True)
    done.wait(60)
    print("bye", flush=True)
    """
)

# Ignores SIGINT and starts a grandchild in its group: both must go on stop().
STUBBORN = textwrap.dedent(
    """
    import signal, subprocess, sys, threading
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # readiness-ok
    print(f"child {child.pid}", flush=True)
    threading.Event().wait(60)
    """
)


def _wait_for_line(proc_log: Path, prefix: str) -> str:
    def line() -> str | None:
        for text in proc_log.read_text().splitlines() if proc_log.exists() else []:
            if text.startswith(prefix):
                return text
        return None

    return wait_until(line, timeout_s=20, what=f"{prefix!r} in {proc_log.name}", interval_s=0.02)


def test_sigint_stops_a_polite_daemon_and_keeps_its_log(tmp_path: Path):
    with ProcessSet(tmp_path) as procs:
        proc = procs.start("polite", [POLITE], argv0=PY)
        _wait_for_line(proc.log_path, "ready")
        result = proc.stop(grace_s=10)
    assert result.returncode == 0 and not result.killed
    assert result.stop_s < 5
    assert "bye" in proc.log_text()


def test_a_daemon_ignoring_sigint_is_killed_with_its_children(tmp_path: Path):
    with ProcessSet(tmp_path) as procs:
        proc = procs.start("stubborn", [STUBBORN], argv0=PY)
        child_pid = int(_wait_for_line(proc.log_path, "child ").split()[1])
        result = proc.stop(grace_s=0.3)
    assert result.killed and result.returncode == -signal.SIGKILL
    assert _gone(child_pid)


def _gone(pid: int, timeout_s: float = 5.0) -> bool:
    """True once `pid` has exited (or is a zombie nobody reaped): SIGKILL is delivered
    asynchronously, so a grandchild may still be listed for a moment after its group was killed."""

    def exited() -> bool:
        try:
            return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
        except psutil.NoSuchProcess:
            return True

    try:
        return bool(wait_until(exited, timeout_s=timeout_s, what=f"pid {pid} to exit"))
    except DaemonError:
        return False


def test_leaving_the_block_by_an_exception_stops_everything(tmp_path: Path):
    pids = []
    with pytest.raises(RuntimeError), ProcessSet(tmp_path) as procs:
        for i in range(2):
            proc = procs.start(f"p{i}", [POLITE], argv0=PY)
            _wait_for_line(proc.log_path, "ready")
            pids.append(proc.pid)
        raise RuntimeError("test body failed")
    assert all(_gone(pid) for pid in pids)


def test_a_daemon_dying_during_a_wait_fails_it_at_once_naming_the_log(tmp_path: Path):
    with ProcessSet(tmp_path) as procs:
        procs.start("crash", ["print('no config here'); raise SystemExit(3)"], argv0=PY)
        with pytest.raises(DaemonError, match=r"crash exited with code 3.*no config here"):
            wait_until(lambda: None, timeout_s=30, what="something", procs=procs)


def test_a_wait_that_times_out_names_what_it_waited_for(tmp_path: Path):
    with pytest.raises(DaemonError, match="the impossible"):
        wait_until(lambda: False, timeout_s=0.2, what="the impossible", interval_s=0.05)


def test_daemons_do_not_get_the_owners_ctrl_c(tmp_path: Path):
    """Each daemon has its own process group: a Ctrl-C at the terminal (SIGINT to the owner's
    group) does not reach it; the owner stops it deliberately."""
    with ProcessSet(tmp_path) as procs:
        proc = procs.start("polite", [POLITE], argv0=PY)
        _wait_for_line(proc.log_path, "ready")
        assert os.getpgid(proc.pid) == proc.pid != os.getpgid(0)
