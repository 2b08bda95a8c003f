"""Daemons as real subprocesses: start, wait for readiness, stop, always clean up.

Shared by `elasticfog demo`, the e2e tests and the benchmarks. Each daemon runs in its own process
group (`start_new_session`), so a signal reaches the daemon and anything it spawned, and a Ctrl-C
typed at the terminal is not delivered to the daemons behind our back: the owner decides how they
stop. Output goes to one log file per daemon, which is what a failing test attaches and what the
demo names when a daemon dies.

Readiness is waited for, never slept for: a liveliness token (`TokenWatch`) or a predicate over a
reply (`wait_until`), each with a timeout and a message naming what did not happen. While waiting
we also watch the processes, so a daemon that exits during startup fails the wait at once with its
exit code and the last line of its log instead of a timeout.

Stopping is SIGINT to the group, then SIGKILL after a grace period. `ProcessSet` owns a set of
daemons and stops them in reverse order of start on exit from its `with` block, on Ctrl-C (a second
one escalates to SIGKILL), on SIGTERM to the owner (turned into the same path) and, as a last
resort, at interpreter exit. `LocalFleet` puts the runtime's daemons on top of that: start them
with the real CLI, wait until each is ready, and watch them as any other machine of the fleet
would (tokens, probes, ctl, the registry's views, the robots' telemetry); in a TLS fleet the
watching session listens on TLS only and shows the registry's certificate (`observer_identity`).
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import IO, TYPE_CHECKING, Any, TypeVar

from common.errors import UserError

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig

log = logging.getLogger(__name__)

STOP_GRACE_S = 3.0
"""How long a daemon gets after SIGINT before its group is killed (daemons promise 2 s)."""

KILL_WAIT_S = 5.0
"""How long to wait for the kernel to reap a SIGKILLed group before giving up on it."""

WATCH_INTERVAL_S = 0.05
"""How often a readiness wait looks at the processes it depends on while it waits for an event."""

LOG_TAIL_LINES = 40
"""Lines of a daemon's log shown when it fails (tests attach this much)."""

T = TypeVar("T")


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


def wait_until(
    fn: Callable[[], T | None],
    *,
    timeout_s: float,
    what: str,
    procs: ProcessSet | Sequence[DaemonProc] | None = None,
    interval_s: float = 0.1,
    wake: threading.Event | None = None,
) -> T:
    """Call `fn` until it returns something other than None/False, and return that.

    For conditions only a query can tell (a registry view, a probe reply). Between attempts we wait
    on `wake` (set it from a callback to retry at once) for at most `interval_s`, and check that the
    daemons in `procs` are still running. `DaemonError` naming `what` after `timeout_s`.
    """
    deadline = time.monotonic() + timeout_s
    wake = wake or threading.Event()
    last_error: Exception | None = None
    while True:
        _check_procs(procs)
        try:
            result = fn()
        except Exception as exc:  # a query that fails now may succeed once the daemon is up
            last_error = exc
            result = None
        if result is not None and result is not False:
            return result
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            detail = f" (last error: {last_error})" if last_error else ""
            raise DaemonError(f"timed out after {timeout_s:.0f} s waiting for {what}{detail}")
        wake.wait(min(interval_s, remaining))
        wake.clear()


def _check_procs(procs: ProcessSet | Sequence[DaemonProc] | None) -> None:
    if procs is None:
        return
    if isinstance(procs, ProcessSet):
        procs.check_alive()
        return
    for proc in procs:
        proc.check_alive()


class TokenWatch:
    """The fleet's liveliness tokens for waits that name keys (`keys.alive_*`), with the daemons'
    processes watched meanwhile.

    The tokens are followed by a `common.membership.MembershipView` of every role (seeded, then
    kept up to date by its subscriber, so a wait never misses a token declared just before it
    began); this adds what starting daemons needs: a wait that fails at once when a daemon exits,
    and a `DaemonError` naming the missing tokens on timeout. Close it (or use `with`) before
    the session closes.
    """

    def __init__(self, session: zenoh.Session, fleet: str) -> None:
        # Imported here: the demo's CLI parsing must not pay for importing zenoh.
        from common.membership import MembershipView

        self.fleet = fleet
        self.view = MembershipView(session, fleet).start()

    @property
    def alive(self) -> set[str]:
        """The keys of the tokens alive now."""
        from common import keys

        members = self.view.snapshot()
        return {keys.alive(self.fleet, role, id) for role, ids in members.items() for id in ids}

    def wait_for(
        self,
        keys: Sequence[str],
        *,
        timeout_s: float,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
        present: bool = True,
    ) -> None:
        """Block until every key is alive (present=False: gone); `DaemonError` on timeout."""
        members = {key: self._member(key) for key in keys}

        def missing(alive: Mapping[str, frozenset[str]]) -> list[str]:
            return [k for k, (role, id) in members.items() if (id in alive[role]) != present]

        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            slice_s = max(0.0, min(WATCH_INTERVAL_S, remaining))
            if self.view.wait_for(lambda alive: not missing(alive), timeout_s=slice_s):
                return
            _check_procs(procs)
            if remaining <= 0:
                state = "liveliness token" if present else "disappearance of token"
                raise DaemonError(
                    f"timed out after {timeout_s:.0f} s waiting for {state} "
                    + ", ".join(missing(self.view.snapshot()))
                )

    def _member(self, key: str) -> tuple[str, str]:
        """(role, id) of a liveliness key of this fleet."""
        from common import keys

        parts = keys.parse_key(key)
        if parts is None or parts.role is None or parts.id is None or parts.fleet != self.fleet:
            raise ValueError(f"{key!r} is not a liveliness key of fleet {self.fleet}")
        return parts.role, parts.id

    def close(self) -> None:
        self.view.close()

    def __enter__(self) -> TokenWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on `host` (the OS picks it; the caller binds it soon after)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


# -- a whole fleet on this host --------------------------------------------------------------------
def merge_into(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """Merge `changes` into `base` in place: nested mappings merge, other values replace."""
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            merge_into(base[key], value)
        else:
            base[key] = value
    return base


def write_local_fleet(
    directory: Path,
    *,
    fleet: str | None = None,
    model: str | None = None,
    port: int | None = None,
    changes: dict[str, Any] | None = None,
    tls: bool = False,
) -> Path:
    """`elasticfog init`'s single-host fleet.yaml with a free registry port and a fleet name of
    its own (two runs on one host never see each other's keys), `changes` merged in, checked
    with `load_fleet`. With `tls`, what `elasticfog init --tls` writes: certificates in
    `directory/certs/`, mutual TLS and access control on every link. Returns the file's path."""
    import uuid

    import yaml

    from common.config import load_fleet
    from common.init_cli import DEFAULT_MODEL, write_fleet

    path = write_fleet(
        Path(directory),
        port=port or free_tcp_port(),
        fleet=fleet or f"local-{uuid.uuid4().hex[:8]}",
        model=model or DEFAULT_MODEL,
        force=True,
        tls=tls,
    )
    if changes:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        merge_into(data, changes)
        path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
        load_fleet(path)  # a bad change fails here, naming the field
    return path


class TelemetryTap:
    """The per-frame telemetry of one robot, received over Zenoh as it happens.

    Records are kept as the robot's JSONL objects plus `at` (completion wall clock) and `epoch`.
    `wait_for` blocks until a record satisfies a predicate; `on_record` callbacks run on the
    subscriber's thread (keep them short).
    """

    def __init__(
        self,
        session: Any,
        key_expr: str,
        on_record: Callable[[dict[str, Any]], None] | None = None,
    ) -> None:
        from common.wire import WireError, decode
        from common.wire.telemetry import TelemetryRecord

        self._decode = lambda data: decode(data, expect=TelemetryRecord)
        self._wire_error = WireError
        self.records: list[dict[str, Any]] = []
        self.bad = 0
        self._on_record = on_record
        self._changed = threading.Condition()
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            message = self._decode(sample.payload.to_bytes())
        except self._wire_error:
            self.bad += 1
            return
        rec: dict[str, Any] = message.to_jsonl()
        rec["at"] = message.at
        rec["epoch"] = message.epoch
        rec["robot"] = message.robot
        with self._changed:
            self.records.append(rec)
            self._changed.notify_all()
        if self._on_record is not None:
            self._on_record(rec)

    def snapshot(self) -> list[dict[str, Any]]:
        with self._changed:
            return list(self.records)

    def wait_for(
        self,
        pred: Callable[[dict[str, Any]], bool],
        *,
        timeout_s: float,
        what: str,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
    ) -> dict[str, Any]:
        """The first record (already received or to come) satisfying `pred`."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        with self._changed:
            while True:
                for rec in self.records[seen:]:
                    if pred(rec):
                        return rec
                seen = len(self.records)
                _check_procs(procs)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DaemonError(f"timed out after {timeout_s:.0f} s waiting for {what}")
                self._changed.wait(min(WATCH_INTERVAL_S * 4, remaining))

    def wait_frame(
        self,
        frame: int,
        *,
        timeout_s: float,
        procs: ProcessSet | Sequence[DaemonProc] | None = None,
    ) -> dict[str, Any]:
        """The first record of a frame >= `frame`."""
        return self.wait_for(
            lambda r: int(r.get("frame", -1)) >= frame,
            timeout_s=timeout_s,
            what=f"telemetry of frame {frame}",
            procs=procs,
        )

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._sub.undeclare()


def link_protocol(cfg: FleetConfig) -> str:
    """The Zenoh protocol of the fleet's links: `tls` in a TLS fleet (nothing listens in
    plaintext), else `tcp`."""
    return "tls" if cfg.tls else "tcp"


def observer_identity(cfg: FleetConfig) -> str | None:
    """Whose certificate a session that watches and drives a fleet shows (this module's, the
    testbed's observer): in a TLS fleet the registry's, since it follows telemetry, reads the
    views and sends ctl, which the access control lets only the registry do; else none."""
    return cfg.registry.id if cfg.tls else None


class LocalFleet:
    """The daemons of one fleet.yaml as subprocesses on this host, and a session to watch them.

    What the demo, the e2e tests and the benchmarks share: start the registry, cloud daemons and
    robots with the real CLI, wait until each is ready (registry: its router accepts connections and
    its liveliness token is up; cloud: its token is up and, if the registry runs, the registry lists
    it as alive; robot: its token), and talk to them as any other machine would — probe and ctl
    keys, the registry's views, the robots' telemetry. The observer session is a peer like the
    daemons, so it keeps seeing the robots and clouds when the registry is gone.
    """

    def __init__(
        self,
        config: Path,
        workdir: Path,
        *,
        env: dict[str, str] | None = None,
        startup_timeout_s: float = 60.0,
    ) -> None:
        from common.config import load_fleet

        self.config = Path(config)
        self.cfg = load_fleet(self.config)
        self.fleet = self.cfg.fleet
        self.workdir = Path(workdir)
        self.startup_timeout_s = startup_timeout_s
        self.procs = ProcessSet(self.workdir / "logs", env=env)
        self._session: Any = None
        self._tokens: TokenWatch | None = None
        self._taps: list[TelemetryTap] = []
        self._restarts: dict[str, int] = {}

    # -- context -----------------------------------------------------------------------------
    def __enter__(self) -> LocalFleet:
        self.procs.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> list[StopResult]:
        """Stop every daemon (robots first), then close the observer session."""
        try:
            return self.procs.close()
        finally:
            for tap in self._taps:
                tap.close()
            self._taps.clear()
            if self._tokens is not None:
                self._tokens.close()
                self._tokens = None
            if self._session is not None:
                with contextlib.suppress(Exception):
                    self._session.close()
                self._session = None

    @property
    def registry_host_port(self) -> tuple[str, int]:
        address = self.cfg.registry.endpoint.partition("/")[2]
        host, _, port = address.rpartition(":")
        return host.strip("[]"), int(port)

    @property
    def session(self) -> Any:
        """The observer's Zenoh peer session (opened on first use)."""
        if self._session is None:
            from common.session import open_session

            self._session = open_session(
                self.cfg,
                identity=observer_identity(self.cfg),
                listen=[f"{link_protocol(self.cfg)}/127.0.0.1:0"],
            )
            self._tokens = TokenWatch(self._session, self.fleet)
        return self._session

    @property
    def tokens(self) -> TokenWatch:
        _ = self.session
        assert self._tokens is not None
        return self._tokens

    # -- starting daemons --------------------------------------------------------------------
    def _name(self, base: str) -> str:
        # A daemon started again (registry restart) gets its own log file.
        count = self._restarts.get(base, 0)
        self._restarts[base] = count + 1
        return base if count == 0 else f"{base}.{count}"

    def start_registry(self, *args: str, wait: bool = True) -> DaemonProc:
        """`elasticfog registry --config F [args]`; with `wait`, until it is ready."""
        from common import keys

        proc = self.procs.start(self._name("registry"), ["registry", *self._config_args, *args])
        if wait:
            host, port = self.registry_host_port
            wait_until(
                lambda: _tcp_accepting(host, port),
                timeout_s=self.startup_timeout_s,
                what=f"the registry's router on {host}:{port}",
                procs=[proc],
                interval_s=WATCH_INTERVAL_S,
            )
            self.tokens.wait_for(
                [keys.alive_registry(self.fleet, self.cfg.registry.id)],
                timeout_s=self.startup_timeout_s,
                procs=[proc],
            )
        return proc

    def start_cloud(self, cloud_id: str, *args: str) -> DaemonProc:
        """`elasticfog cloud --config F --id ID [args]`, not waited for (see `wait_clouds`)."""
        return self.procs.start(
            self._name(cloud_id), ["cloud", *self._config_args, "--id", cloud_id, *args]
        )

    def start_clouds(self, cloud_ids: Sequence[str] | None = None, *args: str) -> list[DaemonProc]:
        """Start cloud daemons side by side, then wait until every one is ready."""
        ids = list(self.cfg.cloud_ids if cloud_ids is None else cloud_ids)
        procs = [self.start_cloud(c, *args) for c in ids]
        self.wait_clouds(ids, procs=procs)
        return procs

    def wait_clouds(
        self, cloud_ids: Sequence[str], *, procs: Sequence[DaemonProc] | None = None
    ) -> None:
        """Until each cloud's token is up and, if a registry runs, it lists them as alive."""
        from common import keys

        self.tokens.wait_for(
            [keys.alive_cloud(self.fleet, c) for c in cloud_ids],
            timeout_s=self.startup_timeout_s,
            procs=procs,
        )
        if self.registry_alive():
            wait_until(
                lambda: self._registered(cloud_ids),
                timeout_s=self.startup_timeout_s,
                what=f"the registry to register {', '.join(cloud_ids)}",
                procs=procs,
            )

    def start_robot(
        self,
        robot_id: str,
        *args: str,
        frames: int | None = None,
        telemetry: Path | None = None,
        wait: bool = False,
    ) -> DaemonProc:
        """`elasticfog robot --config F --id ID [--frames N] [--telemetry FILE] [args]`."""
        from common import keys

        cli = ["robot", *self._config_args, "--id", robot_id]
        if frames is not None:
            cli += ["--frames", str(frames)]
        if telemetry is not None:
            cli += ["--telemetry", str(telemetry)]
        proc = self.procs.start(self._name(robot_id), [*cli, *args])
        if wait:
            self.tokens.wait_for(
                [keys.alive_robot(self.fleet, robot_id)],
                timeout_s=self.startup_timeout_s,
                procs=[proc],
            )
        return proc

    @property
    def _config_args(self) -> list[str]:
        return ["--config", str(self.config)]

    # -- watching ----------------------------------------------------------------------------
    def tap(
        self, robot_id: str, on_record: Callable[[dict[str, Any]], None] | None = None
    ) -> TelemetryTap:
        """Follow `robot_id`'s telemetry from now on (declare before starting the robot)."""
        from common import keys

        tap = TelemetryTap(self.session, keys.tele(self.fleet, robot_id), on_record)
        self._taps.append(tap)
        return tap

    def registry_alive(self) -> bool:
        from common import keys

        return keys.alive_registry(self.fleet, self.cfg.registry.id) in self.tokens.alive

    def query(self, key: str, payload: bytes | None = None, *, timeout_s: float = 2.0) -> list[Any]:
        """Every decoded reply to a get on `key` (ErrorReply included); no reply: []."""
        from common.wire import decode

        kwargs: dict[str, Any] = {"timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = payload
        out = []
        for reply in self.session.get(key, **kwargs):
            if reply.ok is not None:
                out.append(decode(reply.ok.payload.to_bytes()))
        return out

    def view(self, name: str, *, timeout_s: float = 2.0) -> list[Any]:
        """The rows of the registry's view `name` (deployments, robots, routes, events...)."""
        from common import keys
        from common.wire.registry import RIB_VIEW_REPLIES

        expected = RIB_VIEW_REPLIES[name]
        for message in self.query(keys.rib(self.fleet, name), timeout_s=timeout_s):
            if isinstance(message, expected):
                return list(message.rows)  # type: ignore[attr-defined]
            raise DaemonError(f"registry view {name}: unexpected reply {message!r}")
        raise DaemonError(f"no reply from the registry on view {name}")

    def route(self, robot_id: str) -> Any | None:
        """The registry's route row for `robot_id` (None if it has none)."""
        for row in self.view("routes"):
            if row.robot == robot_id:
                return row
        return None

    def _registered(self, cloud_ids: Sequence[str]) -> bool:
        alive = {row.id for row in self.view("deployments", timeout_s=1.0) if row.alive}
        return all(c in alive for c in cloud_ids)

    def probe(self, deployment: str, *, timeout_s: float = 2.0) -> Any:
        """The ProbeReply of `deployment` (DaemonError if it does not answer)."""
        from common import keys
        from common.wire.registry import ProbeReply, ProbeRequest

        request = ProbeRequest(sender="observer", sent_at=time.time()).to_wire()
        key = keys.dep_probe(self.fleet, deployment)
        for message in self.query(key, request, timeout_s=timeout_s):
            if isinstance(message, ProbeReply):
                return message
            raise DaemonError(f"probe of {deployment}: unexpected reply {message!r}")
        raise DaemonError(f"no probe reply from {deployment}")

    def ctl(self, deployment: str, request: Any, *, timeout_s: float = 2.0) -> Any:
        """Send a CtlRequest to `deployment`; its CtlReply (DaemonError if none or refused)."""
        from common import keys
        from common.wire.registry import CtlReply

        key = keys.dep_ctl(self.fleet, deployment)
        for message in self.query(key, request.to_wire(), timeout_s=timeout_s):
            if isinstance(message, CtlReply) and message.ok:
                return message
            raise DaemonError(f"ctl {request.op.value} to {deployment} refused: {message!r}")
        raise DaemonError(f"no ctl reply from {deployment}")

    def set_fault(
        self, deployment: str, *, delay_ms: float = 0.0, drop: float = 0.0, stall: bool = False
    ) -> Any:
        """Fault injection at run time on `deployment`'s ctl key."""
        from common.wire.registry import CtlOp, CtlRequest, FaultSpec

        fault = FaultSpec(delay_ms=delay_ms, drop=drop, stall=stall)
        return self.ctl(deployment, CtlRequest(op=CtlOp.FAULT, fault=fault, sender="observer"))

    # -- stopping ----------------------------------------------------------------------------
    def kill(self, name: str) -> float:
        """SIGKILL daemon `name` (its latest incarnation); returns the wall-clock instant."""
        proc = self.latest(name)
        at = time.time()
        proc.kill()
        return at

    def latest(self, base: str) -> DaemonProc:
        """The most recently started daemon called `base` (or `base.N` after restarts)."""
        for proc in reversed(self.procs.procs):
            if proc.name == base or proc.name.startswith(base + "."):
                return proc
        raise KeyError(base)


def _tcp_accepting(host: str, port: int) -> bool:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((host, port)) == 0
