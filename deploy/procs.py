"""Daemons as real subprocesses: start, stop, always clean up.

Shared by `elasticfog demo`, the e2e tests and the benchmarks. Each daemon runs in its own process
group (`start_new_session`), so a signal reaches the daemon and anything it spawned, and a Ctrl-C
typed at the terminal is not delivered to the daemons behind our back: the owner decides how they
stop. Output goes to one log file per daemon, which is what a failing test attaches and what the
demo names when a daemon dies.

Stopping is SIGINT to the group, then SIGKILL after a grace period. `ProcessSet` owns a set of
daemons and stops them in reverse order of start on exit from its `with` block, on Ctrl-C (a second
one escalates to SIGKILL), on SIGTERM to the owner (turned into the same path) and, as a last
resort, at interpreter exit.

Beside it: `deploy.readiness` (waiting for a daemon to be ready, never sleeping: `wait_until`,
`TokenWatch`), `deploy.telemetry_tap` (a robot's telemetry as it happens) and `deploy.local_fleet`
(a whole fleet.yaml on this host: `LocalFleet`).
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, Any

from common.errors import UserError

log = logging.getLogger(__name__)

STOP_GRACE_S = 3.0
"""How long a daemon gets after SIGINT before its group is killed (daemons promise 2 s)."""

KILL_WAIT_S = 5.0
"""How long to wait for the kernel to reap a SIGKILLed group before giving up on it."""

WATCH_INTERVAL_S = 0.05
"""How often a readiness wait looks at the processes it depends on while it waits for an event."""

LOG_TAIL_LINES = 40
"""Lines of a daemon's log shown when it fails (tests attach this much)."""


class DaemonError(UserError):
    """A daemon exited early or did not become ready in time; the message names it and its log."""


def elasticfog_argv() -> list[str]:
    """The command that runs the `elasticfog` CLI of this very installation.

    The console script next to the interpreter is preferred (readable in `ps`); without it (an
    unusual install) the same entry point is run through the interpreter.
    """
    script = Path(sys.executable).with_name("elasticfog")
    if script.exists():
        return [str(script)]
    found = shutil.which("elasticfog")
    if found:
        return [found]
    return [sys.executable, "-c", "from common.cli import main; main()"]


@dataclass
class StopResult:
    """How a daemon ended: exit code, how long stopping took, whether it had to be killed."""

    name: str
    returncode: int | None
    stop_s: float
    killed: bool


class DaemonProc:
    """One daemon subprocess in its own process group, with its output in `log_path`."""

    def __init__(
        self,
        name: str,
        args: Sequence[str],
        log_path: Path,
        *,
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.name = name
        self.args = list(args)
        self.log_path = Path(log_path)
        self.env = env
        self.cwd = cwd
        self.popen: subprocess.Popen[bytes] | None = None
        self.started_at = 0.0
        self.stop_result: StopResult | None = None
        self.stopping = False  # killed or stopped on purpose: its exit is no failure
        self._log_file: IO[bytes] | None = None

    # -- start / state ---------------------------------------------------------------------
    def start(self) -> DaemonProc:
        """Start the process (own session and process group, output to the log file)."""
        if self.popen is not None:
            raise RuntimeError(f"{self.name} already started")
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log_file = self.log_path.open("ab")
        env = dict(os.environ if self.env is None else self.env)
        # Daemon logs must reach the file as they happen, not when a buffer fills or at exit.
        env.setdefault("PYTHONUNBUFFERED", "1")
        self.started_at = time.monotonic()
        self.popen = self._spawn(self._log_file, env)
        log.debug("started %s (pid %d): %s", self.name, self.popen.pid, " ".join(self.args))
        return self

    def _spawn(self, log_file: IO[bytes], env: dict[str, str]) -> subprocess.Popen[bytes]:
        """Start the process itself (a subclass may start it elsewhere, e.g. in a namespace)."""
        # No preexec_fn: the parent may hold a Zenoh session (threads), and fork+exec without
        # Python code in between is the only safe way to start a process from it.
        return subprocess.Popen(
            self.args,
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=self.cwd,
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        if self.popen is None:
            raise RuntimeError(f"{self.name} not started")
        return self.popen.pid

    def poll(self) -> int | None:
        """The exit code if the process has exited, else None."""
        return None if self.popen is None else self.popen.poll()

    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to exit by itself; `DaemonError` naming the log on timeout."""
        if self.popen is None:
            raise RuntimeError(f"{self.name} not started")
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise DaemonError(
                f"{self.name} did not finish within {timeout_s:.0f} s; log: {self.log_path}"
            ) from None

    def check_alive(self) -> None:
        """Raise `DaemonError` naming the exit code and the log's last line if it has exited."""
        code = self.poll()
        if code is not None:
            last = self.log_tail(1).strip() or "(empty log)"
            raise DaemonError(
                f"{self.name} exited with code {code}; log: {self.log_path}; last line: {last}"
            )

    # -- signals / stop --------------------------------------------------------------------
    def send_signal(self, sig: int) -> None:
        """Signal the whole process group (the daemon and anything it started)."""
        if self.popen is None:
            return
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.popen.pid, sig)

    def kill(self) -> None:
        """SIGKILL the group now (the failover experiments' way of losing a deployment)."""
        self.stopping = True
        self.send_signal(signal.SIGKILL)

    def stop(self, grace_s: float = STOP_GRACE_S, sig: int = signal.SIGINT) -> StopResult:
        """Ask the daemon to stop (`sig` to its group), SIGKILL the group after `grace_s`.

        Idempotent: the second call returns the first result. Whatever happens, the group is gone
        when this returns (or reported killed), and the log file is closed.
        """
        if self.stop_result is not None:
            return self.stop_result
        self.stopping = True
        if self.popen is None:
            self.stop_result = StopResult(self.name, None, 0.0, killed=False)
            return self.stop_result
        t0 = time.monotonic()
        killed = False
        if self.popen.poll() is None:
            self.send_signal(sig)
            try:
                self.popen.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.1f s; killing it", self.name, grace_s)
                killed = True
        # Also reap stragglers in the group (children of the daemon), even after a clean exit.
        self.send_signal(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(timeout=KILL_WAIT_S)
        stop_s = time.monotonic() - t0
        self.stop_result = StopResult(self.name, self.popen.poll(), stop_s, killed)
        self._close_log()
        return self.stop_result

    def _close_log(self) -> None:
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    # -- logs ------------------------------------------------------------------------------
    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def log_tail(self, lines: int = LOG_TAIL_LINES) -> str:
        return "\n".join(self.log_text().splitlines()[-lines:])


class ProcessSet:
    """The daemons one owner started; all of them are stopped when the owner is done.

    Use as a context manager. On exit (normal, exception, Ctrl-C) every daemon still running gets
    SIGINT, then SIGKILL after the grace period, in reverse order of start (robots before clouds
    before the registry: nothing is left waiting for a dead peer). A Ctrl-C during that cleanup
    kills what is left at once. While the set is open, SIGTERM to the owner raises
    KeyboardInterrupt in the main thread so the same cleanup runs.
    """

    def __init__(self, log_dir: Path, *, env: dict[str, str] | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.env = env
        self.procs: list[DaemonProc] = []
        self._lock = threading.Lock()
        self._previous_sigterm: Any = None
        self._closed = False

    def __enter__(self) -> ProcessSet:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        atexit.register(self._atexit_kill)
        if threading.current_thread() is threading.main_thread():
            self._previous_sigterm = signal.signal(signal.SIGTERM, self._on_sigterm)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(
        self,
        name: str,
        cli_args: Sequence[str],
        *,
        env: dict[str, str] | None = None,
        argv0: Sequence[str] | None = None,
    ) -> DaemonProc:
        """Start `elasticfog <cli_args>` (or `argv0 + cli_args`) as daemon `name`."""
        args = [*(elasticfog_argv() if argv0 is None else list(argv0)), *cli_args]
        proc = DaemonProc(name, args, self.log_dir / f"{name}.log", env=env or self.env)
        with self._lock:
            if self._closed:
                raise RuntimeError("process set already closed")
            self.procs.append(proc)
        return proc.start()

    def get(self, name: str) -> DaemonProc:
        for proc in self.procs:
            if proc.name == name:
                return proc
        raise KeyError(name)

    def check_alive(self, names: Sequence[str] | None = None) -> None:
        """Raise `DaemonError` if any daemon (or any of `names`) has exited, except those that
        were stopped or killed on purpose."""
        for proc in self.procs:
            if (names is None or proc.name in names) and not proc.stopping:
                proc.check_alive()

    def stop_all(self, grace_s: float = STOP_GRACE_S) -> list[StopResult]:
        """Stop every daemon, last started first; a Ctrl-C meanwhile kills the rest at once."""
        results: list[StopResult] = []
        pending = list(reversed(self.procs))
        try:
            for proc in pending:
                results.append(proc.stop(grace_s))
        except KeyboardInterrupt:
            for proc in pending:
                proc.kill()
            for proc in pending:
                results.append(proc.stop(grace_s=0.0))
            raise
        return results

    def close(self) -> list[StopResult]:
        if self._closed:
            return [p.stop_result for p in self.procs if p.stop_result is not None]
        try:
            return self.stop_all()
        finally:
            self._closed = True
            if self._previous_sigterm is not None:
                signal.signal(signal.SIGTERM, self._previous_sigterm)
                self._previous_sigterm = None
            atexit.unregister(self._atexit_kill)

    def logs(self) -> dict[str, str]:
        """Every daemon's log tail by name (what a failing test prints)."""
        return {p.name: p.log_tail() for p in self.procs}

    def format_logs(self, lines: int = LOG_TAIL_LINES) -> str:
        parts = []
        for proc in self.procs:
            parts.append(f"----- {proc.name} ({proc.log_path}) -----\n{proc.log_tail(lines)}")
        return "\n".join(parts)

    def _on_sigterm(self, sig: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt(f"received {signal.Signals(sig).name}")

    def _atexit_kill(self) -> None:
        # Last resort when the owner exits without closing (e.g. an unhandled error in a thread).
        for proc in self.procs:
            if proc.running():
                proc.kill()


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on `host` (the OS picks it; the caller binds it soon after)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])
