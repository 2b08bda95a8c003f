"""Pinning a bench's processes to CPUs (`deploy.cpu_pinning`, `bench scale --pin-cloud`): how
CPUs are split, every thread of a running process pinned (and a thread it starts afterwards
too), and the option refused with a clear message where it cannot work (one CPU)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from common.errors import UserError
from deploy.cpu_pinning import off_set_threads, pin_process, split_for_cloud, usable_cpus
from experiments.scale import ScaleOptions

ROOT = Path(__file__).resolve().parents[2]
# A child with three threads besides its main one; on a line from the parent it starts one more
# and prints that thread's CPUs (a thread inherits its creator's mask).
CHILD = """
import os, sys, threading
stop = threading.Event()
for _ in range(3):
    threading.Thread(target=stop.wait, daemon=True).start()
print("ready", flush=True)
sys.stdin.readline()
seen = []
thread = threading.Thread(target=lambda: seen.append(sorted(os.sched_getaffinity(0))))
thread.start()
thread.join()
print(",".join(map(str, seen[0])), flush=True)
"""

needs_two_cpus = pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs this process may run on"
)


def test_the_cloud_gets_a_cpu_per_worker_and_the_rest_keep_one() -> None:
    assert split_for_cloud([0, 1], 2) == split_for_cloud([1, 0], 1)
    two = split_for_cloud([0, 1], 2)
    assert (two.cloud, two.rest) == ((1,), (0,))
    four = split_for_cloud([0, 1, 2, 3], 2)
    assert (four.cloud, four.rest) == ((2, 3), (0, 1))
    many = split_for_cloud(range(8), 16)
    assert (many.cloud, many.rest) == (tuple(range(1, 8)), (0,))


def test_one_cpu_is_refused_naming_the_option_and_the_cpus() -> None:
    with pytest.raises(UserError, match=r"--pin-cloud needs at least 2 CPUs.*may run on 1 \(3\)"):
        split_for_cloud([3], 1)
    with pytest.raises(ValueError, match="wanted"):
        split_for_cloud([0, 1], 0)


def test_scale_options_check_the_split_before_any_daemon_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ScaleOptions(pin_cloud=False).check()
    monkeypatch.setattr("experiments.scale.usable_cpus", lambda: [0])
    ScaleOptions(pin_cloud=False).check()  # not asked for: no refusal
    with pytest.raises(UserError, match="--pin-cloud needs at least 2 CPUs"):
        ScaleOptions(pin_cloud=True).check()
    monkeypatch.setattr("experiments.scale.usable_cpus", lambda: [0, 1, 2])
    options = ScaleOptions(pin_cloud=True, workers=2, deployments=(1,))
    options.check()
    assert options.cpu_split(1).cloud == (1, 2)


def test_bench_scale_refuses_pin_cloud_on_one_cpu() -> None:
    # A real interpreter restricted to one CPU, as a one-CPU container would be.
    code = (
        "import os, sys\n"
        "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n"
        "from common.cli import main\n"
        "sys.argv = ['elasticfog', *sys.argv[1:]]\n"
        "main()\n"
    )
    argv = [sys.executable, "-c", code, "bench", "scale", "--fairness", "--pin-cloud"]
    done = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode != 0
    assert "--pin-cloud needs at least 2 CPUs" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr, done.stderr


@needs_two_cpus
def test_every_thread_of_a_running_process_is_pinned_and_new_threads_follow() -> None:
    cpu = max(usable_cpus())
    with subprocess.Popen(
        [sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    ) as child:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline().strip() == "ready"
        assert off_set_threads(child.pid, {cpu}), "the child starts on every CPU"
        assert pin_process(child.pid, {cpu}) == 4
        assert off_set_threads(child.pid, {cpu}) == []
        child.stdin.write("go\n")
        child.stdin.flush()
        assert child.stdout.readline().strip() == str(cpu)
        assert child.wait(timeout=30) == 0


def test_a_process_that_is_gone_is_named() -> None:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    with pytest.raises(UserError, match=f"cannot pin process {gone.pid}: it is gone"):
        pin_process(gone.pid, {0})
