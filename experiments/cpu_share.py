"""Who used the host's CPUs during a measurement phase: the bench's own processes, and the rest.

A latency measured on a shared host says little unless one knows what else ran meanwhile. A
`CpuMeter` reads, at the start and the end of a phase, the CPU seconds (user + system) of each
process the bench started, split for the cloud daemon into its Zenoh threads (receiving,
decoding and admitting or refusing requests: Zenoh runs the query callbacks) and its other
threads (the workers: decoding tensors, running the suffix, replying), and the busy and stolen
seconds of every CPU from /proc/stat. `CpuMeter.usage` turns two readings into cores (CPU
seconds per second): what each process used, what everything else on the host used ("others":
busy time of all CPUs not accounted for by the bench's processes), how much of it fell on the
deployment's CPUs, and the time the hypervisor took (steal).
"""

from __future__ import annotations

import re
import time
from collections.abc import Collection, Mapping
from dataclasses import dataclass

import psutil

ZENOH_THREAD = re.compile(r"(rx|tx|net|acc|app)-\d+")
"""Names of the Zenoh runtime's threads (the query callbacks run on them); Python's threads
carry the process's name."""


@dataclass(frozen=True)
class CpuReading:
    """CPU seconds used so far, at monotonic time `at`."""

    at: float
    processes: dict[str, float]
    zenoh_threads: dict[str, dict[int, float]]
    """Per process, the CPU seconds of each Zenoh thread alive at the reading, by thread id."""
    busy: dict[int, float]
    steal: dict[int, float]


def _busy_and_steal() -> tuple[dict[int, float], dict[int, float]]:
    busy, steal = {}, {}
    for cpu, t in enumerate(psutil.cpu_times(percpu=True)):
        # guest time is counted in user already; iowait is idle time.
        busy[cpu] = t.user + t.nice + t.system + t.irq + t.softirq
        steal[cpu] = getattr(t, "steal", 0.0)
    return busy, steal


def _zenoh_thread_s(proc: psutil.Process) -> dict[int, float]:
    seconds = {}
    for thread in proc.threads():
        try:
            with open(f"/proc/{proc.pid}/task/{thread.id}/comm") as comm:
                name = comm.read().strip()
        except OSError:
            continue  # the thread ended
        if ZENOH_THREAD.fullmatch(name):
            seconds[thread.id] = thread.user_time + thread.system_time
    return seconds


def _zenoh_thread_delta_s(before: Mapping[int, float], after: Mapping[int, float]) -> float:
    """CPU seconds the Zenoh threads used between two readings, thread by thread: a thread alive
    at both counts its difference, one born in between its whole life, and one that ended in
    between is left out (its last seconds cannot be read). Never the difference of two sums over
    different sets of threads, which goes negative when a thread ends between the readings."""
    # max(0, ...): a thread id reused by a newer thread with less time so far.
    return sum(max(0.0, s - before.get(tid, 0.0)) for tid, s in after.items())


class CpuMeter:
    """Readings of the named processes (`processes`: name -> pid) and of the host's CPUs.

    `cloud` names the deployment's process among them: its Zenoh threads' share is read too, and
    with `cloud_cpus` (the CPUs it is pinned to) so is the busy time others had on those CPUs.
    """

    def __init__(
        self,
        processes: Mapping[str, int],
        *,
        cloud: str | None = None,
        cloud_cpus: Collection[int] | None = None,
    ) -> None:
        if cloud is not None and cloud not in processes:
            raise ValueError(f"cloud {cloud!r} is not one of the processes")
        self._procs = {name: psutil.Process(pid) for name, pid in processes.items()}
        self._cloud = cloud
        self._cloud_cpus = None if cloud_cpus is None else sorted(cloud_cpus)

    def read(self) -> CpuReading:
        at = time.monotonic()
        spent, zenoh = {}, {}
        for name, proc in self._procs.items():
            try:
                times = proc.cpu_times()
                spent[name] = float(times.user + times.system)
                if name == self._cloud:
                    zenoh[name] = _zenoh_thread_s(proc)
            except psutil.NoSuchProcess:
                spent[name] = float("nan")  # gone: its share cannot be told
        busy, steal = _busy_and_steal()
        return CpuReading(at, spent, zenoh, busy, steal)

    def usage(self, start: CpuReading, end: CpuReading) -> dict[str, float]:
        """Cores (CPU seconds per second) used between two readings: `<name>_cores` per
        process, `<cloud>_zenoh_cores`, `others_cores` (busy time of the host's CPUs that the
        processes do not account for), with `cloud_cpus` `others_on_cloud_cpus_cores` (busy time
        of those CPUs beyond the cloud's own), and `steal_cores`."""
        seconds = end.at - start.at
        if seconds <= 0:
            raise ValueError("the readings must be in time order")

        def cores(before: float, after: float) -> float:
            return (after - before) / seconds

        out = {
            f"{name}_cores": cores(start.processes[name], spent)
            for name, spent in end.processes.items()
        }
        busy = {cpu: cores(start.busy[cpu], end.busy[cpu]) for cpu in end.busy}
        out["others_cores"] = max(0.0, sum(busy.values()) - sum(out.values()))
        if self._cloud is not None:
            out[f"{self._cloud}_zenoh_cores"] = (
                _zenoh_thread_delta_s(
                    start.zenoh_threads[self._cloud], end.zenoh_threads[self._cloud]
                )
                / seconds
            )
            if self._cloud_cpus is not None:
                on_cloud_cpus = sum(busy[cpu] for cpu in self._cloud_cpus)
                own = out[f"{self._cloud}_cores"]
                out["others_on_cloud_cpus_cores"] = max(0.0, on_cloud_cpus - own)
        out["steal_cores"] = sum(cores(start.steal[c], end.steal[c]) for c in end.steal)
        return out
