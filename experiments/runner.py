"""The testbed fleet runner: a namespace testbed, the real daemons inside it, and cleanup.

`TestbedFleet` is what every experiment and the multi-host e2e tests use:

    with TestbedFleet(workdir) as tf:                      # testbed up (root), always down again
        tf.launch(FleetSpec(fleet=tf.next_fleet_name(), clouds=["edge-1"]))
        tf.shape_robot(20)                                 # tc cap on the robot's uplink
        robot = tf.start_robot("elastic", frames=60, cpu_fraction=0.05)
        tf.follower.wait_frame(30, timeout_s=60, procs=[robot])
        tf.shape_robot(3)                                  # a glitch while the robot streams
        tf.finish_robot(timeout_s=120)
        records = tf.follower.records()                    # the robot's --telemetry JSONL

Each host of the fleet is a namespace of one testbed (`deploy.testbed`): the registry with its
router on `registry`, cloud daemons on `edge-1`, `edge-2`, `cloud-1`, `cloud-2`, the robot on
`robot`, and an observer (`experiments.observer`) on `bench`, through which the runner
waits for readiness (liveliness tokens, the registry's views) and injects faults. Daemons are
started with `Testbed.popen`, so each runs inside its host's namespace and CPU cgroup, in its own
process group, with its output in a log file (`deploy.procs.DaemonProc`).

`TestbedFleet(workdir, tls=True)` runs every fleet with mutual TLS and the access control on
(`experiments.fleet`: certificates with the hosts' testbed addresses, `tls/` endpoints).

Cleanup always happens, in this order: the robot, the clouds and the registry get SIGINT then
SIGKILL (`deploy.procs.ProcessSet`), the observer is told to quit, and `Testbed.down()` removes
the namespaces (their veths and qdiscs go with them), the cgroups and any process still inside.
That runs on a normal exit, on an exception, on Ctrl-C and on SIGTERM (turned into the same
path); a second Ctrl-C during cleanup cannot interrupt the removal of the testbed.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from common import keys
from common.config import FleetConfig
from common.errors import UserError
from deploy.procs import DaemonError, DaemonProc, ProcessSet, elasticfog_argv
from deploy.readiness import wait_until
from deploy.testbed import Testbed, require_root

from .fleet import (
    CLOUD_HOSTS,
    OBSERVER_HOST,
    OBSERVER_PORT,
    REGISTRY_HOST,
    ROBOT_HOST,
    ROBOT_ID,
    FleetSpec,
    endpoint,
    write_fleet,
    write_robot_variant,
)

DEFAULT_HOSTS = (REGISTRY_HOST, ROBOT_HOST, *CLOUD_HOSTS, OBSERVER_HOST)
STARTUP_TIMEOUT_S = 90.0
"""Per daemon: Python, onnxruntime and Zenoh start on 2 cores shared with everything else."""
OBSERVER_REPLY_S = 10.0
"""Bound of an observer request beyond its own timeout (its process may be descheduled)."""
OBSERVER_QUIT_S = 3.0
FOLLOW_POLL_S = 0.05
"""How often the telemetry file is read while a wait is on."""


class NetnsDaemon(DaemonProc):
    """A daemon started inside a testbed host (its namespace and CPU cgroup)."""

    def __init__(
        self,
        testbed: Testbed,
        host: str,
        name: str,
        args: Sequence[str],
        log_path: Path,
        *,
        env: dict[str, str] | None = None,
    ) -> None:
        super().__init__(name, args, log_path, env=env)
        self.testbed = testbed
        self.host = host

    def _spawn(self, log_file: IO[bytes], env: dict[str, str]) -> subprocess.Popen[bytes]:
        return self.testbed.popen(
            self.host,
            self.args,
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            env=env,
        )


class ObserverClient:
    """The runner's side of `experiments.observer`: one request at a time."""

    def __init__(self, testbed: Testbed, config: Path, log_path: Path) -> None:
        self.testbed = testbed
        self.config = config
        self.log_path = log_path
        self._proc: subprocess.Popen[str] | None = None
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._next_id = 0
        self._log: IO[bytes] | None = None

    def start(self, timeout_s: float = STARTUP_TIMEOUT_S, *, tls: bool = False) -> None:
        listen = endpoint(self.testbed.address(OBSERVER_HOST), OBSERVER_PORT, tls=tls)
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = self.log_path.open("ab")
        argv = [sys.executable, "-m", "experiments.observer"]
        self._proc = self.testbed.popen(
            OBSERVER_HOST,
            [*argv, "--config", str(self.config), "--listen", listen],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env=env,
        )
        threading.Thread(target=self._read, name="observer-reader", daemon=True).start()
        event = self._next_line(timeout_s, "the observer's session")
        if json.loads(event).get("event") != "ready":
            raise DaemonError(f"observer: unexpected first line {event!r}; log: {self.log_path}")

    def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def _next_line(self, timeout_s: float, what: str) -> str:
        try:
            line = self._lines.get(timeout=timeout_s)
        except queue.Empty:
            raise DaemonError(
                f"the observer did not answer within {timeout_s:.0f} s waiting for {what}; "
                f"log: {self.log_path}"
            ) from None
        if line is None:
            raise DaemonError(f"the observer exited; log: {self.log_path}")
        return line

    def call(self, op: str, *, timeout_s: float = 5.0, **args: Any) -> dict[str, Any]:
        """Send one request; its reply (`DaemonError` naming the problem if it failed)."""
        if self._proc is None or self._proc.stdin is None:
            raise RuntimeError("observer not started")
        self._next_id += 1
        request = {"id": self._next_id, "op": op, "timeout_s": timeout_s, **args}
        self._proc.stdin.write(json.dumps(request) + "\n")
        self._proc.stdin.flush()
        deadline = time.monotonic() + timeout_s + OBSERVER_REPLY_S
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            reply = json.loads(self._next_line(remaining, f"{op}"))
            if reply.get("id") != self._next_id:
                continue  # the late answer to a request that already timed out here
            if not reply.get("ok"):
                raise DaemonError(f"observer {op}: {reply.get('error')}")
            return dict(reply)

    def wait_tokens(
        self, token_keys: Sequence[str], timeout_s: float, present: bool = True
    ) -> None:
        self.call("wait_tokens", keys=list(token_keys), present=present, timeout_s=timeout_s)

    def view(self, name: str, timeout_s: float = 2.0) -> list[dict[str, Any]]:
        return list(self.call("view", name=name, timeout_s=timeout_s)["rows"])

    def fault(
        self, deployment: str, *, delay_ms: float = 0.0, drop: float = 0.0, stall: bool = False
    ) -> None:
        self.call("fault", deployment=deployment, delay_ms=delay_ms, drop=drop, stall=stall)

    def close(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            with contextlib.suppress(OSError, ValueError):
                assert proc.stdin is not None
                proc.stdin.write(json.dumps({"op": "quit"}) + "\n")
                proc.stdin.close()
            try:
                proc.wait(timeout=OBSERVER_QUIT_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=OBSERVER_QUIT_S)
            if proc.stdout is not None:
                proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None


class TelemetryFollower:
    """The robot's `--telemetry` JSONL file, read as it grows (it is on the shared filesystem)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._records: list[dict[str, Any]] = []
        self._offset = 0
        self._partial = b""

    def poll(self) -> list[dict[str, Any]]:
        """Read what was appended since the last call; returns every record so far."""
        try:
            with self.path.open("rb") as f:
                f.seek(self._offset)
                chunk = f.read()
        except FileNotFoundError:
            return self._records
        self._offset += len(chunk)
        lines = (self._partial + chunk).split(b"\n")
        self._partial = lines.pop()  # an unfinished last line waits for its newline
        for line in lines:
            if not line.strip():
                continue
            with contextlib.suppress(ValueError):  # JSON or UTF-8 errors: a torn line
                obj = json.loads(line)
                if isinstance(obj, dict):
                    self._records.append(obj)
        return self._records

    def records(self) -> list[dict[str, Any]]:
        return list(self.poll())

    def last_frame(self) -> int:
        """The highest frame reported so far (-1: none)."""
        return max((int(r.get("frame", -1)) for r in self.poll()), default=-1)

    def wait_for(
        self,
        pred: Callable[[dict[str, Any]], bool],
        *,
        timeout_s: float,
        what: str,
        procs: Sequence[DaemonProc] = (),
    ) -> dict[str, Any]:
        """The first record satisfying `pred` (already written or to come), within `timeout_s`.

        A robot that exits before writing it fails the wait at once, naming its log."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        while True:
            records = self.poll()
            for rec in records[seen:]:
                if pred(rec):
                    return rec
            seen = len(records)
            for proc in procs:
                if proc.poll() is not None:
                    self.poll()
                    for rec in self._records[seen:]:
                        if pred(rec):
                            return rec
                    proc.check_alive()
                    raise DaemonError(f"{proc.name} finished before {what}; log: {proc.log_path}")
            if time.monotonic() >= deadline:
                raise DaemonError(f"timed out after {timeout_s:.0f} s waiting for {what}")
            time.sleep(FOLLOW_POLL_S)

    def wait_frame(
        self, frame: int, *, timeout_s: float, procs: Sequence[DaemonProc] = ()
    ) -> dict[str, Any]:
        """The first record of a frame >= `frame`."""
        return self.wait_for(
            lambda r: int(r.get("frame", -1)) >= frame,
            timeout_s=timeout_s,
            what=f"telemetry of frame {frame}",
            procs=procs,
        )


class TestbedFleet:
    """A testbed with the fleet's daemons in its hosts; see the module docstring.

    One testbed serves several runs: `launch` starts a fresh registry and clouds for a new fleet
    (new name, new RIB), `stop_daemons` stops them, and the robot may be started many times.
    """

    __test__ = False  # not a pytest test class despite the name

    def __init__(
        self,
        workdir: Path,
        *,
        name: str | None = None,
        hosts: Sequence[str] = DEFAULT_HOSTS,
        startup_timeout_s: float = STARTUP_TIMEOUT_S,
        log: Callable[[str], None] | None = None,
        tls: bool = False,
    ) -> None:
        self.workdir = Path(workdir)
        self.tls = tls
        """Mutual TLS and access control on every link of every run."""
        self.testbed = Testbed(name or f"efb-{os.getpid() % 100000}", hosts=hosts)
        self.startup_timeout_s = startup_timeout_s
        self.log = log or (lambda message: None)
        self.procs = ProcessSet(self.workdir / "logs")
        self.observer: ObserverClient | None = None
        self.config: Path | None = None
        self.cfg: FleetConfig | None = None
        self.follower: TelemetryFollower = TelemetryFollower(self.workdir / "none.jsonl")
        self.robot: NetnsDaemon | None = None
        self.runs = 0
        self.measure_from = 0
        """The first frame of the latest robot run that ran under its CPU quota."""
        # What `__enter__` made, released by `close` in reverse: the daemons stopped, the process
        # set closed, the testbed removed.
        self._owned = contextlib.ExitStack()

    # -- lifecycle ---------------------------------------------------------------------------
    def __enter__(self) -> TestbedFleet:
        require_root()
        self.workdir.mkdir(parents=True, exist_ok=True)
        with contextlib.ExitStack() as owned:
            # Removed last, also after a half-made `up()`.
            owned.callback(self._testbed_down)
            # The process set next: from here SIGTERM is a KeyboardInterrupt and takes the same
            # cleanup path as Ctrl-C.
            owned.enter_context(self.procs)
            self.log(f"testbed {self.testbed.name}: up")
            self.testbed.up()
            owned.callback(self.stop_daemons)
            self._owned = owned.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop every daemon, close the process set and remove the testbed (each step runs even
        if the one before failed); safe to call twice."""
        self._owned.close()

    def _testbed_down(self) -> None:
        # Removing the testbed must finish even if the user presses Ctrl-C again.
        with _sigint_ignored():
            self.testbed.down()
        self.log(f"testbed {self.testbed.name}: down")

    @property
    def tb(self) -> Testbed:
        return self.testbed

    def next_fleet_name(self, tag: str = "run") -> str:
        """A fleet name of its own for the next run (keys never mix between runs)."""
        self.runs += 1
        return f"{tag}{self.runs}-{os.getpid() % 100000}"

    # -- daemons -----------------------------------------------------------------------------
    def launch(
        self,
        spec: FleetSpec,
        *,
        prepare: bool = True,
        wait_registered: bool = True,
    ) -> FleetConfig:
        """Write the run's fleet, start the observer, the registry and the clouds; wait until
        the registry lists every cloud as alive."""
        self.stop_daemons()
        run_dir = self.workdir / spec.fleet
        self.config, self.cfg = write_fleet(spec, self.testbed.addresses(), run_dir, tls=self.tls)
        if self.tls:
            self.log(f"{spec.fleet}: mutual TLS and access control on every link")
        if prepare:
            _prepare_model(self.cfg)
        self.observer = ObserverClient(self.testbed, self.config, run_dir / "observer.log")
        self.observer.start(self.startup_timeout_s, tls=self.tls)
        self.start_registry()
        self.start_clouds(list(spec.clouds), wait_registered=wait_registered)
        return self.cfg

    def _start(self, host: str, name: str, cli_args: Sequence[str]) -> NetnsDaemon:
        assert self.config is not None
        proc = NetnsDaemon(
            self.testbed,
            host,
            name,
            [*elasticfog_argv(), *cli_args],
            self.config.parent / "logs" / f"{name}.log",
        )
        # Owned by the process set: stopped (robots first) whatever happens.
        self.procs.procs.append(proc)
        proc.start()
        return proc

    def start_registry(self) -> NetnsDaemon:
        """The registry (and its router) on the `registry` host, waited for by its token."""
        cfg, _ = self._require_run()
        self.log("starting the registry")
        proc = self._start(
            REGISTRY_HOST, self._unique(REGISTRY_HOST), ["registry", "--config", str(self.config)]
        )
        self._wait_token(keys.alive_registry(cfg.fleet, cfg.registry.id), proc)
        return proc

    def start_clouds(
        self, deployment_ids: Sequence[str], *, wait_registered: bool = True
    ) -> list[NetnsDaemon]:
        """Cloud daemons on their hosts, side by side; waits for their tokens and, with
        `wait_registered`, until the registry lists them as alive."""
        cfg, observer = self._require_run()
        self.log(f"starting {', '.join(deployment_ids)}")
        procs = [
            self._start(c, self._unique(c), ["cloud", "--config", str(self.config), "--id", c])
            for c in deployment_ids
        ]
        for cloud, proc in zip(deployment_ids, procs, strict=True):
            self._wait_token(keys.alive_deployment(cfg.fleet, cloud), proc)
        if wait_registered:
            wanted = set(deployment_ids)

            def registered() -> bool:
                rows = observer.view("deployments", timeout_s=2.0)
                return wanted <= {r["id"] for r in rows if r.get("alive")}

            wait_until(
                registered,
                timeout_s=self.startup_timeout_s,
                what=f"the registry to register {', '.join(deployment_ids)}",
                procs=procs,
                interval_s=0.2,
            )
        return procs

    def start_robot(
        self,
        policy: str | None = None,
        *,
        frames: int,
        fps: float | None = None,
        cpu_fraction: float | None = None,
        extra: Sequence[str] = (),
        tag: str = "",
    ) -> NetnsDaemon:
        """`elasticfog robot` on the `robot` host writing its telemetry to a JSONL file.

        The robot starts with the whole machine (Python and onnxruntime start-up is not what is
        measured); once its token is up, its host gets `cpu_fraction` of a core. The first frame
        reported after that is `self.measure_from`."""
        cfg, _ = self._require_run()
        if self.robot is not None and self.robot.running():
            raise RuntimeError("a robot is already running")
        self.testbed.cpu(ROBOT_HOST, None)
        name = self._unique(f"{ROBOT_ID}{'-' + tag if tag else ''}")
        assert self.config is not None
        telemetry = self.config.parent / f"{name}.jsonl"
        self.follower = TelemetryFollower(telemetry)
        config = self.config
        if policy is not None:
            config, policy_kind = write_robot_variant(self.config, policy)
        args = ["robot", "--config", str(config), "--id", ROBOT_ID]
        args += ["--frames", str(frames), "--telemetry", str(telemetry)]
        if policy is not None:
            args += ["--policy", policy_kind]
        if fps is not None:
            args += ["--fps", f"{fps:g}"]
        self.log(f"starting {ROBOT_ID} ({policy or cfg.policy.kind}, {frames} frames)")
        self.robot = self._start(ROBOT_HOST, name, [*args, *extra])
        self._wait_token(keys.alive_robot(cfg.fleet, ROBOT_ID), self.robot)
        if cpu_fraction is not None:
            self.testbed.cpu(ROBOT_HOST, cpu_fraction)
        self.measure_from = self.follower.last_frame() + 2  # the frame in flight ran unthrottled
        return self.robot

    def finish_robot(self, timeout_s: float) -> list[dict[str, Any]]:
        """Wait for the robot to run its frames and exit; its telemetry records."""
        if self.robot is None:
            raise RuntimeError("no robot started")
        code = self.robot.wait(timeout_s)
        self.testbed.cpu(ROBOT_HOST, None)
        if code != 0:
            raise DaemonError(
                f"{self.robot.name} exited with code {code}; log: {self.robot.log_path}; "
                f"last line: {self.robot.log_tail(1).strip() or '(empty log)'}"
            )
        return self.follower.records()

    def stop_robot(self) -> None:
        # The quota goes first: a robot held at a few % of a core takes seconds to shut down.
        with contextlib.suppress(UserError):
            self.testbed.cpu(ROBOT_HOST, None)
        if self.robot is not None:
            self.robot.stop()

    def stop_daemons(self) -> None:
        """Stop every daemon of the current run and the observer (the testbed stays up); CPU
        quotas are lifted first, so that a Ctrl-C does not wait on a daemon shutting down at a
        few % of a core."""
        for host in self.testbed.hosts:
            with contextlib.suppress(UserError, OSError):
                self.testbed.cpu(host, None)
        try:
            self.procs.stop_all()
        finally:
            self.procs.procs.clear()
            if self.observer is not None:
                self.observer.close()
                self.observer = None
            self.robot = None

    def daemon(self, name: str) -> NetnsDaemon:
        """The latest daemon started under `name` (a host name or `robot-1`)."""
        for proc in reversed(self.procs.procs):
            if proc.name == name or proc.name.startswith(name + "."):
                assert isinstance(proc, NetnsDaemon)
                return proc
        raise KeyError(name)

    # -- conditions --------------------------------------------------------------------------
    def shape_robot(self, uplink_mbit: float | None, downlink_mbit: float | None = None) -> None:
        """Cap the robot's uplink (and downlink) now, also while it streams."""
        self.testbed.shape(ROBOT_HOST, uplink_mbit, downlink_mbit)

    def cpu_robot(self, fraction: float | None) -> None:
        """Give the robot's host `fraction` of one core now (None: no cap)."""
        self.testbed.cpu(ROBOT_HOST, fraction)

    def reset_conditions(self) -> None:
        """No caps, no quotas, every link up, on every host."""
        for host in self.testbed.hosts:
            self.testbed.link(host, True)
            self.testbed.shape(host, None)
            with contextlib.suppress(UserError):
                self.testbed.cpu(host, None)

    # -- helpers -----------------------------------------------------------------------------
    def _require_run(self) -> tuple[FleetConfig, ObserverClient]:
        if self.cfg is None or self.observer is None:
            raise RuntimeError("no run launched")
        return self.cfg, self.observer

    def _unique(self, base: str) -> str:
        names = {p.name for p in self.procs.procs}
        if base not in names:
            return base
        n = 1
        while f"{base}.{n}" in names:
            n += 1
        return f"{base}.{n}"

    def _wait_token(self, key: str, proc: DaemonProc) -> None:
        """Wait for `key`'s liveliness token, failing at once (with the log) if `proc` dies."""
        _, observer = self._require_run()
        deadline = time.monotonic() + self.startup_timeout_s
        while True:
            proc.check_alive()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DaemonError(
                    f"{proc.name} did not declare {key} within {self.startup_timeout_s:.0f} s; "
                    f"log: {proc.log_path}"
                )
            try:
                # Short slices: a daemon that exits meanwhile is noticed within one.
                observer.wait_tokens([key], timeout_s=min(2.0, remaining))
                return
            except DaemonError as exc:
                if "timed out" not in str(exc):
                    raise


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _prepare_model(cfg: FleetConfig) -> None:
    """Split and verify the model into the cache once, before any daemon starts: they load it
    (and never race each other exporting it)."""
    from deploy.demo import prepare_model

    prepare_model(cfg)
