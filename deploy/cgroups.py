"""CPU budgets for testbed hosts with a cgroup-v1 `cpu` controller (CFS bandwidth control).

Each host of a testbed gets one cgroup, `<cpu mount>/elasticfog/<testbed>/<host>`. Every process the
testbed starts on that host is placed in it before it executes, so `cpu.cfs_quota_us` caps the
host as a whole: a fraction of 0.5 means all its processes together get half of one core per
period, whatever they spawn. The files are plain sysfs writes; nothing here runs a subprocess.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from common.errors import UserError

PROC_MOUNTS = Path("/proc/mounts")
CGROUP_ROOT_DIR = "elasticfog"
# The kernel's default CFS period; quotas are expressed against it.
CFS_PERIOD_US = 100_000
# The kernel refuses quotas below 1 ms.
MIN_QUOTA_US = 1_000
MIN_FRACTION = MIN_QUOTA_US / CFS_PERIOD_US


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


def fraction_to_quota_us(fraction: float | None) -> int:
    """The cfs quota for `fraction` of one core per period; None (no limit) is -1."""
    if fraction is None:
        return -1
    if not MIN_FRACTION <= fraction <= (os.cpu_count() or 1):
        raise UserError(
            f"cpu fraction {fraction:g} is out of range: use {MIN_FRACTION:g} to "
            f"{os.cpu_count() or 1} (cores of this machine)"
        )
    return max(MIN_QUOTA_US, round(fraction * CFS_PERIOD_US))


class CpuGroup:
    """One host's cgroup: create, set the quota, list and place processes, remove."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @property
    def procs_file(self) -> Path:
        """Writing a pid here moves that process (with its threads) into the group."""
        return self.path / "cgroup.procs"

    def create(self) -> None:
        """Make the group (and its parents); a no-op if it exists."""
        self.path.mkdir(parents=True, exist_ok=True)
        (self.path / "cpu.cfs_period_us").write_text(str(CFS_PERIOD_US))

    def exists(self) -> bool:
        """True when the group's directory is there."""
        return self.procs_file.exists()

    def set_fraction(self, fraction: float | None) -> None:
        """Cap the group at `fraction` of one core (None removes the cap)."""
        (self.path / "cpu.cfs_quota_us").write_text(str(fraction_to_quota_us(fraction)))

    def fraction(self) -> float | None:
        """The cap now in force, read back from the kernel; None when unlimited."""
        quota = int((self.path / "cpu.cfs_quota_us").read_text())
        period = int((self.path / "cpu.cfs_period_us").read_text())
        return None if quota < 0 else quota / period

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
