"""Pin processes, every thread of them, to a set of CPUs: a deployment's cores to itself in a bench.

Why every thread: on Linux `sched_setaffinity(tid)` sets the mask of one thread (a pid is its
main thread's id), and a new thread inherits the mask of the thread that creates it. So pinning a
running process means setting the mask of each thread in `/proc/PID/task`; a thread created while
that goes on may inherit the old mask from a thread not yet pinned, so passes repeat until one
finds every thread already on the set. Descendant processes are pinned the same way.

Why affinity and not a cpuset cgroup: a cpuset needs root and a mounted cpuset hierarchy, and it
would not keep anyone else off the cores either (that takes moving every other process of the
host into a narrower set, which a bench must not do to processes it does not own). Affinity needs
neither, and pins exactly what the bench started. Other processes of the host may still run on
the pinned cores; `experiments.cpu_share` measures how much they did.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import psutil

from common.errors import UserError

PIN_PASSES = 10
"""Passes over a process's threads before giving up on one that keeps creating threads."""


@dataclass(frozen=True)
class CpuSplit:
    """The CPUs the deployments run on, and the ones everything else of the bench runs on."""

    cloud: tuple[int, ...]
    rest: tuple[int, ...]


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity, which a container may narrow)."""
    if not hasattr(os, "sched_getaffinity"):
        raise UserError("pinning to CPUs needs Linux (sched_setaffinity); this system has none")
    return sorted(os.sched_getaffinity(0))


def split_for_cloud(cpus: Sequence[int], wanted: int) -> CpuSplit:
    """The last `wanted` of `cpus` for the deployments, at most all but one; the rest for the
    load generators and the registry (they need a core too, or they would share the cloud's)."""
    if len(cpus) < 2:
        listed = ", ".join(map(str, cpus)) or "none"
        raise UserError(
            f"--pin-cloud needs at least 2 CPUs, one for the cloud daemons and one for the load "
            f"generators; this process may run on {len(cpus)} ({listed})"
        )
    if wanted < 1:
        raise ValueError(f"wanted must be >= 1, got {wanted}")
    count = min(wanted, len(cpus) - 1)
    ordered = sorted(cpus)
    return CpuSplit(cloud=tuple(ordered[-count:]), rest=tuple(ordered[:-count]))


def _tree(pid: int, children: bool) -> list[psutil.Process]:
    try:
        proc = psutil.Process(pid)
        return [proc, *(proc.children(recursive=True) if children else [])]
    except psutil.NoSuchProcess:
        raise UserError(f"cannot pin process {pid}: it is gone") from None


def _threads(proc: psutil.Process) -> list[int]:
    try:
        return [thread.id for thread in proc.threads()]
    except psutil.NoSuchProcess:
        return []  # a descendant that ended meanwhile has nothing left to pin


def off_set_threads(pid: int, cpus: Collection[int], *, children: bool = True) -> list[int]:
    """Threads of `pid` (and of its descendants) whose CPU mask is not exactly `cpus`."""
    wanted = set(cpus)
    off = []
    for proc in _tree(pid, children):
        for tid in _threads(proc):
            try:
                if os.sched_getaffinity(tid) != wanted:
                    off.append(tid)
            except ProcessLookupError:
                continue  # the thread ended
    return off


def pin_process(pid: int, cpus: Collection[int], *, children: bool = True) -> int:
    """Every thread of `pid` (and of its descendants, with `children`) on `cpus`; the number of
    threads found on the set at the end. UserError naming the process when the kernel refuses."""
    wanted = set(cpus)
    if not wanted:
        raise ValueError("an empty CPU set")
    for _ in range(PIN_PASSES):
        off = off_set_threads(pid, wanted, children=children)
        if not off:
            return sum(len(_threads(proc)) for proc in _tree(pid, children))
        for tid in off:
            try:
                os.sched_setaffinity(tid, wanted)
            except ProcessLookupError:
                continue  # the thread ended
            except OSError as exc:
                raise UserError(
                    f"cannot pin thread {tid} of process {pid} to CPUs "
                    f"{','.join(map(str, sorted(wanted)))}: {exc.strerror}"
                ) from None
    raise UserError(
        f"process {pid} kept starting threads on other CPUs through {PIN_PASSES} passes; "
        "it could not be pinned"
    )
