"""CPU budgets for testbed hosts with a cgroup-v1 `cpu` controller (CFS bandwidth control).

Each host of a testbed gets one cgroup, `<cpu mount>/elasticfog/<testbed>/<host>`. Every process the
testbed starts on that host is placed in it before it executes, so `cpu.cfs_quota_us` caps the
host as a whole: a fraction of 0.5 means all its processes together get half of one core per
period, whatever they spawn. The files are plain sysfs writes; nothing here runs a subprocess.

The period matters as much as the share. A throttled group runs its quota, then waits for the
next period, so a task's wall time moves in steps of one period: with the kernel's default of
100 ms, 0.02 core means 2 ms of CPU then 98 ms of nothing, and a robot's frame times come out in
0.1 s steps. The period here defaults to `DEFAULT_CFS_PERIOD_US` (5 ms) and is lengthened only as
far as the kernel's 1 ms minimum quota requires (see `cfs_bandwidth`). One floor remains that no
period removes: code that never enters the kernel (inference, a busy loop) is charged only at
scheduler ticks (4 ms at HZ = 250), so it runs about a tick and then waits tick ÷ share; the
figures are in docs/testbed.md.
"""

from __future__ import annotations

import errno
import math
import os
from pathlib import Path

from common.errors import UserError

PROC_MOUNTS = Path("/proc/mounts")
CGROUP_ROOT_DIR = "elasticfog"
# The kernel's limits on CFS bandwidth control (`tg_set_cfs_bandwidth`; writes outside them are
# EINVAL, checked on this machine): a period of 1 ms to 1 s, a quota of at least 1 ms.
MIN_PERIOD_US = 1_000
MAX_PERIOD_US = 1_000_000
MIN_QUOTA_US = 1_000
# The period a quota is spread over when the share allows it: short, so a capped host's CPU comes
# in small slices and its task times are not quantized in 100 ms steps (the kernel's default
# period), yet long enough that the group's period timer fires 200 times a second, not the
# 1 ms minimum's 1000.
DEFAULT_CFS_PERIOD_US = 5_000
# The smallest share possible at all: a 1 ms quota in the longest (1 s) period.
MIN_FRACTION = MIN_QUOTA_US / MAX_PERIOD_US
# Read-back shares are rounded to this many significant digits: a quota is whole microseconds,
# so 0.03 core (1000 µs per 33334 µs) would otherwise read 0.0299994.
FRACTION_DIGITS = 4


def find_cpu_mount(mounts_file: Path = PROC_MOUNTS) -> Path | None:
    """Where the cgroup-v1 hierarchy carrying the `cpu` controller is mounted, or None."""
    try:
        lines = mounts_file.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        fields = line.split()
        if len(fields) < 4 or fields[2] != "cgroup":
            continue
        if "cpu" in fields[3].split(","):
            path = Path(fields[1])
            if (path / "cpu.cfs_quota_us").exists():
                return path
    return None


def cfs_bandwidth(
    fraction: float | None, period_us: int = DEFAULT_CFS_PERIOD_US
) -> tuple[int, int]:
    """(cfs_quota_us, cfs_period_us) for `fraction` of one core; None (no limit) is quota -1.

    The period is `period_us` unless the quota would fall below the kernel's 1 ms minimum: then
    the period is lengthened until the quota is exactly that minimum (0.05 core: 1 ms every
    20 ms; 0.02 core: 1 ms every 50 ms). Refusing such shares instead would force every caller
    to work out a period per share, and would break the small robot shares the experiments use
    (0.02 to 0.1 core, all below the 0.2 core that 1 ms in 5 ms allows); the shortest period at
    which the share is still a 1 ms quota is also the finest time grain the kernel can give that
    share, which is what the short period is for. Only a share below `MIN_FRACTION` (1 ms per
    1 s) is an error.
    """
    if not MIN_PERIOD_US <= period_us <= MAX_PERIOD_US:
        raise UserError(
            f"cfs period {period_us} µs is out of range: the kernel takes {MIN_PERIOD_US} to "
            f"{MAX_PERIOD_US} µs"
        )
    if fraction is None:
        return -1, period_us
    cores = os.cpu_count() or 1
    if not MIN_FRACTION <= fraction <= cores or not math.isfinite(fraction):
        raise UserError(
            f"cpu fraction {fraction:g} is out of range: use {MIN_FRACTION:g} (a {MIN_QUOTA_US} µs "
            f"quota, the kernel's least, every {MAX_PERIOD_US} µs) to {cores} (cores of this "
            "machine)"
        )
    period = max(period_us, math.ceil(MIN_QUOTA_US / fraction))
    return max(MIN_QUOTA_US, round(fraction * period)), period


class CpuGroup:
    """One host's cgroup: create, set the quota, list and place processes, remove.

    `period_us` is the CFS period its quotas are spread over (lengthened for small shares, see
    `cfs_bandwidth`).
    """

    def __init__(self, path: Path, *, period_us: int = DEFAULT_CFS_PERIOD_US) -> None:
        cfs_bandwidth(None, period_us)  # checks the period
        self.path = path
        self.period_us = period_us

    @property
    def procs_file(self) -> Path:
        """Writing a pid here moves that process (with its threads) into the group."""
        return self.path / "cgroup.procs"

    def create(self) -> None:
        """Make the group (and its parents); a no-op if it exists."""
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / "cpu.cfs_period_us").write_text(str(self.period_us))

    def exists(self) -> bool:
        """True when the group's directory is there."""
        return self.procs_file.exists()

    def set_fraction(self, fraction: float | None) -> None:
        """Cap the group at `fraction` of one core (None removes the cap)."""
        quota_us, period_us = cfs_bandwidth(fraction, self.period_us)
        # The period first: the kernel checks each write against the other value in force, and
        # any old quota (at least 1 ms, or -1) is valid with any new period.
        (self.path / "cpu.cfs_period_us").write_text(str(period_us))
        (self.path / "cpu.cfs_quota_us").write_text(str(quota_us))

    def bandwidth_us(self) -> tuple[int, int]:
        """(cfs_quota_us, cfs_period_us) now in force; quota -1 when unlimited."""
        quota = int((self.path / "cpu.cfs_quota_us").read_text())
        period = int((self.path / "cpu.cfs_period_us").read_text())
        return quota, period

    def fraction(self) -> float | None:
        """The cap now in force, read back from the kernel; None when unlimited."""
        quota, period = self.bandwidth_us()
        return None if quota < 0 else float(f"{quota / period:.{FRACTION_DIGITS}g}")

    def throttled(self) -> dict[str, int]:
        """The kernel's `cpu.stat` counters (nr_periods, nr_throttled, throttled_time in ns)."""
        stats: dict[str, int] = {}
        for line in (self.path / "cpu.stat").read_text().splitlines():
            key, _, value = line.partition(" ")
            if value.strip().isdigit():
                stats[key] = int(value)
        return stats

    def pids(self) -> list[int]:
        """Processes in the group now (empty when the group does not exist)."""
        try:
            text = self.procs_file.read_text()
        except OSError:
            return []
        return [int(p) for p in text.split()]

    def add(self, pid: int) -> None:
        """Move a running process into the group."""
        self.procs_file.write_text(str(pid))

    def remove(self) -> bool:
        """Remove the group once it holds no process; True if it was removed here."""
        try:
            self.path.rmdir()
        except FileNotFoundError:
            return False
        except OSError as exc:
            if exc.errno == errno.EBUSY:
                raise UserError(f"cgroup {self.path} still holds processes {self.pids()}") from exc
            raise
        return True


def remove_empty_dir(path: Path) -> bool:
    """rmdir a cgroup directory left without children; False if absent or still in use."""
    try:
        path.rmdir()
    except OSError:
        return False
    return True
