"""Multi-host testbed on one machine: network namespaces, a bridge, `tc` shaping and CPU quotas.

Each host of the testbed is a network namespace `<name>.<host>` with its own loopback and an `eth0`
that is one end of a veth pair; the other ends are ports of a bridge living in a namespace of its
own (`<name>._br`). Nothing is created in the machine's own network namespace, so the private
subnet (10.77.0.0/24 by default) exists only between the testbed's hosts and cannot leak out;
two testbeds with different names may even use the same subnet. Inside every host, `/etc/hosts`
names the other hosts (through `/etc/netns/<ns>/hosts`, which `ip netns exec` mounts), so a fleet
file can say `tcp/registry:7447` in the testbed and in docker-compose alike.

Real mechanisms, no mocks: bandwidth caps are `tc` htb classes on the veth (egress inside the host
is its uplink, egress on the bridge port its downlink; see `deploy.shaping`), CPU budgets are a
cgroup-v1 CFS quota per host (see `deploy.cgroups`) that every process started with `popen` or
`exec` is placed in before it runs. Everything needs root.

Lifecycle: `up()` builds it all and writes a state file (under /run) so that `attach()` and
`down()` from another process find it. `down()` is idempotent and also cleans what a crashed run
left behind: it finds namespaces, `/etc/netns` entries and cgroups by the testbed's name prefix,
stops every process still running in them (SIGTERM, then SIGKILL), then removes them. The context
manager form always calls `down()`.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import psutil

from common.errors import UserError
from deploy import shaping
from deploy.cgroups import CGROUP_ROOT_DIR, CpuGroup, find_cpu_mount, remove_empty_dir
from deploy.testbed_defaults import DEFAULT_HOSTS, DEFAULT_NAME, DEFAULT_SUBNET

STATE_DIR_ENV = "ELASTICFOG_TESTBED_STATE_DIR"
DEFAULT_STATE_DIR = Path("/run/elasticfog/testbed")
NETNS_DIR = Path("/run/netns")
ETC_NETNS_DIR = Path("/etc/netns")
HOST_DEV = "eth0"
BRIDGE_DEV = "br0"
BRIDGE_NS_SUFFIX = "_br"
SH = "/bin/sh"
# `ip`/`tc` calls finish in milliseconds; a hung one must not hang the caller.
TOOL_TIMEOUT_S = 10.0
# Stopping a host's processes: SIGTERM, this long to exit, then SIGKILL and this long again.
STOP_GRACE_S = 2.0
KILL_WAIT_S = 2.0
EXIT_POLL_S = 0.02
NAME_RE = re.compile(r"^[a-z][a-z0-9-]{0,15}$")
HOST_RE = re.compile(r"^[a-z][a-z0-9-]{0,31}$")
MAX_HOSTS = 250


class TestbedError(UserError):
    """A testbed operation failed; the message names the command or the thing at fault."""

    __test__ = False  # not a pytest test class despite the name


def require_root() -> None:
    """Raise a clear error unless running as root."""
    if os.geteuid() != 0:
        raise TestbedError(
            "the testbed needs root (it creates network namespaces, tc qdiscs and cgroups): "
            "run it as root or with sudo"
        )


def require_tool(tool: str) -> str:
    """Absolute path of an iproute2 tool, or a clear error."""
    path = shutil.which(tool) or shutil.which(tool, path="/usr/sbin:/sbin:/usr/bin:/bin")
    if path is None:
        raise TestbedError(f"`{tool}` not found on PATH: install iproute2")
    return path


def state_dir() -> Path:
    """Where state files live: $ELASTICFOG_TESTBED_STATE_DIR or /run/elasticfog/testbed."""
    return Path(os.environ.get(STATE_DIR_ENV) or DEFAULT_STATE_DIR)


def check_name(name: str) -> str:
    """Validate a testbed name (it prefixes namespaces and cgroups)."""
    if not NAME_RE.match(name):
        raise TestbedError(
            f"bad testbed name {name!r}: use 1-16 of a-z, 0-9 and '-', starting with a letter"
        )
    return name


def check_hosts(hosts: Iterable[str]) -> tuple[str, ...]:
    """Validate host names: unique, DNS-like, at least one."""
    names = tuple(hosts)
    if not names:
        raise TestbedError("a testbed needs at least one host")
    for host in names:
        if not HOST_RE.match(host):
            raise TestbedError(
                f"bad host name {host!r}: use 1-32 of a-z, 0-9 and '-', starting with a letter"
            )
    duplicates = sorted({h for h in names if names.count(h) > 1})
    if duplicates:
        raise TestbedError(f"host names appear twice: {', '.join(duplicates)}")
    if len(names) > MAX_HOSTS:
        raise TestbedError(f"{len(names)} hosts is too many: at most {MAX_HOSTS}")
    return names


def _check_subnet(subnet: str, n_hosts: int) -> ipaddress.IPv4Network:
    try:
        net = ipaddress.IPv4Network(subnet, strict=True)
    except ValueError as exc:
        raise TestbedError(f"bad subnet {subnet!r}: {exc}") from None
    if not net.is_private:
        raise TestbedError(f"subnet {subnet} is not a private range: use e.g. {DEFAULT_SUBNET}")
    if net.num_addresses - 2 < n_hosts:
        raise TestbedError(f"subnet {subnet} has too few addresses for {n_hosts} hosts")
    return net


class Testbed:
    """One testbed: hosts as network namespaces on a private bridge, shaping and CPU quotas.

    `Testbed(name, hosts)` does no I/O; `up()` builds it, `attach(name)` opens one built by another
    process. Use it as a context manager to always clean up:

        with Testbed("ef", hosts=["registry", "robot", "edge-1"]) as tb:
            tb.shape("robot", uplink_mbit=2)
            proc = tb.popen("robot", ["elasticfog", "robot", ...])
    """

    __test__ = False  # not a pytest test class despite the name

    def __init__(
        self,
        name: str = DEFAULT_NAME,
        hosts: Sequence[str] = DEFAULT_HOSTS,
        subnet: str = DEFAULT_SUBNET,
    ) -> None:
        self.name = check_name(name)
        self.hosts = check_hosts(hosts)
        self.subnet = subnet
        net = _check_subnet(subnet, len(self.hosts))
        host_ips = net.hosts()
        self._addresses = {host: str(next(host_ips)) for host in self.hosts}
        self._prefixlen = net.prefixlen
        self._cpu_mount: Path | None = None

    # -- naming ----------------------------------------------------------------------------
    @property
    def bridge_netns(self) -> str:
        """Namespace of the bridge (no host can be `_br`: host names start with a letter)."""
        return f"{self.name}.{BRIDGE_NS_SUFFIX}"

    @property
    def state_file(self) -> Path:
        """This testbed's state file."""
        return state_dir() / f"{self.name}.json"

    def _check_host(self, host: str) -> str:
        if host not in self._addresses:
            raise TestbedError(
                f"unknown host {host!r} in testbed {self.name}: hosts are {', '.join(self.hosts)}"
            )
        return host

    def netns(self, host: str) -> str:
        """The network namespace name of `host` (for `ip netns exec`)."""
        return f"{self.name}.{self._check_host(host)}"

    def address(self, host: str) -> str:
        """The IPv4 address of `host` on the testbed bridge."""
        return self._addresses[self._check_host(host)]

    def addresses(self) -> dict[str, str]:
        """host → address, in host order."""
        return dict(self._addresses)

    def bridge_port(self, host: str) -> str:
        """The bridge-side end of `host`'s veth pair (its egress is the host's downlink)."""
        return f"v{self.hosts.index(self._check_host(host))}"

    def _cgroup_base(self) -> Path | None:
        if self._cpu_mount is None:
            self._cpu_mount = find_cpu_mount()
        if self._cpu_mount is None:
            return None
        return self._cpu_mount / CGROUP_ROOT_DIR / self.name

    def cgroup(self, host: str) -> CpuGroup | None:
        """`host`'s CPU cgroup, or None when this machine has no cgroup-v1 cpu controller."""
        base = self._cgroup_base()
        return None if base is None else CpuGroup(base / self._check_host(host))

    # -- lifecycle -------------------------------------------------------------------------
    @classmethod
    def attach(cls, name: str = DEFAULT_NAME) -> Testbed:
        """Open a testbed that `up()` built, possibly in another process, from its state file."""
        check_name(name)
        require_root()  # everything after this enters namespaces or writes cgroups
        path = state_dir() / f"{name}.json"
        try:
            state = json.loads(path.read_text())
        except FileNotFoundError:
            if _namespaces_with_prefix(f"{name}."):
                raise TestbedError(
                    f"testbed {name} has namespaces but no state file {path} (left by a crashed "
                    f"run?): clean it with `elasticfog testbed down --name {name}`"
                ) from None
            raise TestbedError(
                f"testbed {name} is not up: start it with `elasticfog testbed up --name {name}`"
            ) from None
        except (OSError, ValueError) as exc:
            raise TestbedError(f"cannot read testbed state {path}: {exc}") from None
        try:
            testbed = cls(state["name"], state["hosts"], state["subnet"])
        except (KeyError, TypeError) as exc:
            raise TestbedError(f"testbed state {path} is malformed (missing {exc})") from None
        if not testbed.is_up():
            raise TestbedError(
                f"testbed {name} is in {path} but its namespaces are gone: "
                f"run `elasticfog testbed down --name {name}` and `up` again"
            )
        return testbed

    def is_up(self) -> bool:
        """True when the bridge and every host namespace exist."""
        existing = set(_namespaces_with_prefix(f"{self.name}."))
        return {self.bridge_netns, *(self.netns(h) for h in self.hosts)} <= existing

    def up(self) -> dict[str, str]:
        """Build the testbed; returns host → address. Cleans up after itself if a step fails."""
        require_root()
        require_tool("ip")
        leftovers = _namespaces_with_prefix(f"{self.name}.")
        if leftovers or self.state_file.exists():
            raise TestbedError(
                f"testbed {self.name} already exists ({', '.join(leftovers) or self.state_file}):"
                f" remove it with `elasticfog testbed down --name {self.name}` or use another name"
            )
        try:
            self._build()
        except BaseException:
            # A half-built testbed is worse than none: undo every step, then report the failure.
            with contextlib.suppress(Exception):
                self.down()
            raise
        return self.addresses()

    def _build(self) -> None:
        br = self.bridge_netns
        self._ip("netns", "add", br)
        self._ip("-n", br, "link", "add", "name", BRIDGE_DEV, "type", "bridge")
        self._ip("-n", br, "link", "set", BRIDGE_DEV, "up")
        base = self._cgroup_base()
        hosts_file = self._hosts_file_text()
        for host in self.hosts:
            ns, port = self.netns(host), self.bridge_port(host)
            self._ip("netns", "add", ns)
            # Both ends are created directly inside namespaces: nothing appears in the root one.
            self._ip(
                *("-n", br, "link", "add", "name", port, "type", "veth"),
                *("peer", "name", HOST_DEV, "netns", ns),
            )
            self._ip("-n", br, "link", "set", port, "master", BRIDGE_DEV, "up")
            self._ip(
                "-n", ns, "addr", "add", f"{self.address(host)}/{self._prefixlen}", "dev", HOST_DEV
            )
            # One wire packet per skb (no 64 KiB GSO bursts): a capped link then paces every
            # packet like a real NIC, and measured goodput matches the cap minus header overhead.
            self._ip("-n", ns, "link", "set", HOST_DEV, "gso_max_segs", "1", "up")
            self._ip("-n", ns, "link", "set", "lo", "up")
            etc = ETC_NETNS_DIR / ns
            etc.mkdir(parents=True, exist_ok=True)
            (etc / "hosts").write_text(hosts_file)
            if base is not None:
                CpuGroup(base / host).create()
        self._write_state()

    def _hosts_file_text(self) -> str:
        lines = ["127.0.0.1\tlocalhost", "::1\tlocalhost ip6-localhost ip6-loopback"]
        lines += [f"{address}\t{host}" for host, address in self._addresses.items()]
        return "\n".join(lines) + "\n"

    def _write_state(self) -> None:
        state = {
            "name": self.name,
            "hosts": list(self.hosts),
            "subnet": self.subnet,
            "addresses": self.addresses(),
            "bridge_netns": self.bridge_netns,
            "cgroup": None if self._cgroup_base() is None else str(self._cgroup_base()),
            "created_by_pid": os.getpid(),
            "created_at": time.time(),
        }
        path = self.state_file
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(state, indent=2) + "\n")
        tmp.replace(path)  # atomic: a reader sees the old file or the whole new one

    def down(self) -> list[str]:
        """Remove everything of this testbed, found by name prefix; returns what was removed.

        Idempotent, and safe after a crash: it does not need the state file or the host list.
        """
        require_root()
        removed: list[str] = []
        prefix = f"{self.name}."
        namespaces = _namespaces_with_prefix(prefix)
        base = self._cgroup_base()
        groups = (
            [CpuGroup(p) for p in sorted(base.iterdir()) if p.is_dir()]
            if base is not None and base.is_dir()
            else []
        )
        pids: set[int] = set()
        if namespaces:
            ip = require_tool("ip")
            for ns in namespaces:
                pids.update(_netns_pids(ip, ns))
        for group in groups:
            pids.update(group.pids())
        stopped = stop_processes(pids)
        removed += [f"process {pid}" for pid in stopped]
        # Hosts first: deleting a host namespace deletes its veth pair; the bridge goes last.
        for ns in sorted(namespaces, key=lambda n: n == self.bridge_netns):
            self._ip("netns", "delete", ns, check=False)
            if not (NETNS_DIR / ns).exists():
                removed.append(f"netns {ns}")
        if ETC_NETNS_DIR.is_dir():
            for etc in sorted(ETC_NETNS_DIR.glob(f"{glob_escape(prefix)}*")):
                shutil.rmtree(etc, ignore_errors=True)
                removed.append(f"netns-config {etc}")
            remove_empty_dir(ETC_NETNS_DIR)
        errors: list[str] = []
        for group in groups:
            try:
                if group.remove():
                    removed.append(f"cgroup {group.path}")
            except UserError as exc:
                errors.append(str(exc))
        if base is not None and remove_empty_dir(base):
            removed.append(f"cgroup {base}")
            remove_empty_dir(base.parent)  # shared by all testbeds: only if this was the last
        with contextlib.suppress(FileNotFoundError):
            self.state_file.unlink()
            removed.append(f"state {self.state_file}")
        if remove_empty_dir(state_dir()) and state_dir() == DEFAULT_STATE_DIR:
            remove_empty_dir(DEFAULT_STATE_DIR.parent)
        if errors:
            raise TestbedError("; ".join(errors))
        return removed

    def __enter__(self) -> Testbed:
        self.up()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.down()

    # -- shaping and CPU -------------------------------------------------------------------
    def shape(
        self, host: str, uplink_mbit: float | None, downlink_mbit: float | None = None
    ) -> None:
        """Cap `host`'s link; None leaves that direction unlimited. Callable while traffic flows.

        Each call sets both directions: `shape(h, 4)` after `shape(h, 4, 2)` lifts the downlink cap.
        """
        self._check_host(host)
        shaping.check_rate(uplink_mbit, "uplink")
        shaping.check_rate(downlink_mbit, "downlink")
        self._require_up()
        self._cap(self.netns(host), HOST_DEV, uplink_mbit)
        self._cap(self.bridge_netns, self.bridge_port(host), downlink_mbit)

    def _cap(self, ns: str, dev: str, mbit: float | None) -> None:
        installed = shaping.has_cap(self._tc(ns, "qdisc", "show", "dev", dev))
        if mbit is None:
            if installed:
                self._tc(ns, *shaping.remove_command(dev))
            return
        commands = shaping.change_commands if installed else shaping.install_commands
        for args in commands(dev, mbit):
            self._tc(ns, *args)

    def link_rates(self, host: str) -> dict[str, float | None]:
        """The caps in force now, read back from the kernel: {uplink_mbit, downlink_mbit}."""
        self._check_host(host)
        return {
            "uplink_mbit": self._read_cap(self.netns(host), HOST_DEV),
            "downlink_mbit": self._read_cap(self.bridge_netns, self.bridge_port(host)),
        }

    def _read_cap(self, ns: str, dev: str) -> float | None:
        if shutil.which("tc") is None:
            return None
        return shaping.parse_class_rate_mbit(self._tc(ns, "class", "show", "dev", dev))

    def cpu(self, host: str, fraction: float | None) -> None:
        """Cap the processes started on `host` at `fraction` of one core (None: no cap).

        The cap is shared by all of the host's processes and applies at once to running ones.
        """
        self._check_host(host)
        group = self.cgroup(host)
        if group is None:
            raise TestbedError(
                "no cgroup-v1 cpu controller is mounted (looked in /proc/mounts): "
                "CPU quotas are not available on this machine"
            )
        self._require_up()
        if not group.exists():
            raise TestbedError(f"cgroup {group.path} of host {host} is missing")
        group.set_fraction(fraction)

    def cpu_fraction(self, host: str) -> float | None:
        """The CPU cap of `host` now in force (None: no cap or no cgroup)."""
        group = self.cgroup(host)
        return group.fraction() if group is not None and group.exists() else None

    def link(self, host: str, up: bool) -> None:
        """Cut (`up=False`) or restore `host`'s link, as if its cable were pulled."""
        self._require_up()
        # The bridge port goes down: the host keeps its address and routes but loses carrier.
        self._ip(
            "-n", self.bridge_netns, "link", "set", self.bridge_port(host), "up" if up else "down"
        )

    def counters(self, host: str) -> dict[str, int]:
        """Bytes and packets through `host`'s eth0 since `up()`: rx/tx bytes and packets."""
        out = self._ip("-n", self.netns(host), "-j", "-s", "link", "show", "dev", HOST_DEV)
        try:
            stats = json.loads(out)[0]["stats64"]
            return {
                "rx_bytes": int(stats["rx"]["bytes"]),
                "tx_bytes": int(stats["tx"]["bytes"]),
                "rx_packets": int(stats["rx"]["packets"]),
                "tx_packets": int(stats["tx"]["packets"]),
            }
        except (ValueError, LookupError, TypeError) as exc:
            raise TestbedError(f"cannot read counters of {host}: {exc}") from None

    # -- processes -------------------------------------------------------------------------
    def popen(self, host: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start `argv` on `host`: inside its namespace and CPU cgroup, in its own process group.

        Keyword arguments go to `subprocess.Popen` (stdout, env, cwd, text...); pass
        `start_new_session=False` to keep the caller's process group (an interactive command).
        """
        ns = self.netns(host)
        if not argv:
            raise TestbedError("no command given to run on the host")
        self._require_up()
        command = [require_tool("ip"), "netns", "exec", ns, *argv]
        group = self.cgroup(host)
        if group is not None and group.exists():
            # The shell joins the cgroup, then execs `ip netns exec`, which execs argv: the same
            # pid all along, so the quota applies from the first instruction of the command.
            join = 'echo $$ > "$1" && shift && exec "$@"'
            command = [SH, "-c", join, "sh", str(group.procs_file), *command]
        kwargs.setdefault("start_new_session", True)
        return subprocess.Popen(command, **kwargs)

    def exec(
        self, host: str, argv: Sequence[str], *, timeout_s: float = 60.0, **kwargs: Any
    ) -> subprocess.CompletedProcess[Any]:
        """Run `argv` on `host` to completion, like `subprocess.run` (`capture_output`, `text`...).

        On timeout the command's process group is killed and `subprocess.TimeoutExpired` raised.
        """
        if kwargs.pop("capture_output", False):
            kwargs["stdout"] = kwargs["stderr"] = subprocess.PIPE
        with self.popen(host, argv, **kwargs) as proc:
            try:
                out, err = proc.communicate(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                _kill_group(proc.pid)
                proc.communicate()
                raise
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)

    def pids(self, host: str) -> list[int]:
        """Processes running on `host` now (in its namespace or its cgroup)."""
        ns = self.netns(host)
        found: set[int] = set()
        if (NETNS_DIR / ns).exists():
            found.update(_netns_pids(require_tool("ip"), ns))
        group = self.cgroup(host)
        if group is not None:
            found.update(group.pids())
        found.discard(os.getpid())
        return sorted(found)

    def kill(self, host: str, sig: int = signal.SIGKILL) -> list[int]:
        """Send `sig` to every process on `host` (e.g. to kill a daemon's host); returns pids."""
        pids = self.pids(host)
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        return pids

    # -- status ----------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """What is up now: per host its namespace, address, caps, CPU quota and processes."""
        up = self.is_up()
        hosts: dict[str, Any] = {}
        for host in self.hosts:
            entry: dict[str, Any] = {"netns": self.netns(host), "address": self.address(host)}
            if up:
                entry.update(self.link_rates(host))
                entry["cpu_fraction"] = self.cpu_fraction(host)
                entry["pids"] = self.pids(host)
                entry.update(self.counters(host))
            hosts[host] = entry
        return {"name": self.name, "up": up, "subnet": self.subnet, "hosts": hosts}

    # -- helpers ---------------------------------------------------------------------------
    def _require_up(self) -> None:
        if not (NETNS_DIR / self.bridge_netns).exists():
            raise TestbedError(
                f"testbed {self.name} is not up: start it with "
                f"`elasticfog testbed up --name {self.name}`"
            )

    def _ip(self, *args: str, check: bool = True) -> str:
        return run_tool([require_tool("ip"), *args], check=check)

    def _tc(self, ns: str, *args: str) -> str:
        return run_tool([require_tool("tc"), "-n", ns, *args])


def run_tool(argv: Sequence[str], *, check: bool = True) -> str:
    """Run an iproute2 command; a failure becomes one line naming the command and its error."""
    try:
        done = subprocess.run(
            list(argv), capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired:
        raise TestbedError(f"`{_show(argv)}` did not finish in {TOOL_TIMEOUT_S:g} s") from None
    if check and done.returncode != 0:
        reason = done.stderr.strip() or done.stdout.strip() or f"exit {done.returncode}"
        raise TestbedError(f"`{_show(argv)}` failed: {' '.join(reason.split())}")
    return done.stdout


def _show(argv: Sequence[str]) -> str:
    return " ".join([Path(argv[0]).name, *argv[1:]])


def glob_escape(text: str) -> str:
    """Escape glob metacharacters (names are validated, but a prefix must match literally)."""
    return re.sub(r"([*?\[])", r"[\1]", text)


def _namespaces_with_prefix(prefix: str) -> list[str]:
    try:
        return sorted(n for n in os.listdir(NETNS_DIR) if n.startswith(prefix))
    except FileNotFoundError:
        return []


def _netns_pids(ip: str, ns: str) -> list[int]:
    out = run_tool([ip, "netns", "pids", ns], check=False)
    return [int(p) for p in out.split() if p.isdigit() and int(p) != os.getpid()]


def _kill_group(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal.SIGKILL)


def _gone(proc: psutil.Process) -> bool:
    try:
        return proc.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_gone(procs: list[psutil.Process], timeout_s: float) -> list[psutil.Process]:
    """Wait (bounded) until the processes have exited; returns those still alive.

    Polls instead of `wait()`: a process may be the caller's child whose exit status its
    `Popen` object must still collect, so it is never reaped here.
    """
    deadline = time.monotonic() + timeout_s
    alive = [p for p in procs if not _gone(p)]
    while alive and time.monotonic() < deadline:
        time.sleep(EXIT_POLL_S)
        alive = [p for p in alive if not _gone(p)]
    return alive


def stop_processes(pids: Iterable[int]) -> list[int]:
    """SIGTERM the processes, SIGKILL those still running after a grace time; returns the pids."""
    procs: list[psutil.Process] = []
    for pid in sorted(set(pids) - {os.getpid()}):
        with contextlib.suppress(psutil.Error):
            proc = psutil.Process(pid)
            if not _gone(proc):
                proc.send_signal(signal.SIGTERM)
                procs.append(proc)
    alive = _wait_gone(procs, STOP_GRACE_S)
    for proc in alive:
        with contextlib.suppress(psutil.Error):
            proc.send_signal(signal.SIGKILL)
    # A process stuck in the kernel may outlive SIGKILL for a while; removal of its cgroup then
    # fails with a message naming it, which beats waiting here without bound.
    _wait_gone(alive, KILL_WAIT_S)
    return [p.pid for p in procs]
