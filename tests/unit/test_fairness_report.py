"""The fairness bench's figures without daemons: CPU shares read from /proc for this very process
(`cpu_share`), the part of a frame's latency outside the deployment's wait and run, medians over
phases, and the report's tables (pinned or not, with CPU figures missing)."""

from __future__ import annotations

import os
import threading
import time

import pytest

from experiments.cpu_share import CpuMeter
from experiments.fairness import KINDS, fairness_markdown, phase_medians, transport_p95_s
from experiments.load_generator import FrameOutcome, FrameRecord

BURN_S = 0.2


def burn(seconds: float) -> None:
    """Use `seconds` of this process's CPU time (however long a busy host makes that take)."""
    until = time.process_time() + seconds
    while time.process_time() < until:
        pass


def test_the_meter_sees_this_process_use_a_core() -> None:
    meter = CpuMeter({"cloud": os.getpid()}, cloud="cloud", cloud_cpus=[0])
    start = meter.read()
    burn(BURN_S)
    end = meter.read()
    used = meter.usage(start, end)
    # /proc counts in clock ticks (10 ms at the usual 100 Hz).
    assert used["cloud_cores"] * (end.at - start.at) == pytest.approx(BURN_S, abs=0.05), used
    # The burn ran on this (Python) thread, not on a Zenoh one. Zenoh threads may be there
    # (sessions that other tests in this process opened leave the runtime's threads running),
    # with a few percent of a core at most.
    assert used["cloud_zenoh_cores"] < used["cloud_cores"] / 2, used
    assert {"others_cores", "others_on_cloud_cpus_cores", "steal_cores"} <= set(used)
    assert all(value >= 0 for value in used.values()), used
    with pytest.raises(ValueError, match="time order"):
        meter.usage(meter.read(), start)


def zenoh_named_thread(burn_s: float, done: threading.Event) -> threading.Thread:
    """A thread named like a Zenoh runtime thread that has used `burn_s` of CPU when this
    returns, and ends once `done` is set."""
    burnt = threading.Event()

    def run() -> None:
        with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as comm:
            comm.write("rx-99")
        burn(burn_s)
        burnt.set()
        done.wait(10)

    thread = threading.Thread(target=run)
    thread.start()
    assert burnt.wait(10), "the named thread did not finish its burn"
    return thread


def test_a_zenoh_thread_that_ends_between_readings_takes_no_seconds_away() -> None:
    """Regression: the share was the difference of two sums over the threads alive at each
    reading, so a thread that ended in between (a session an earlier test closed) made it
    negative (-2.5 cores in a CI run)."""
    meter = CpuMeter({"cloud": os.getpid()}, cloud="cloud")
    first_done, second_done = threading.Event(), threading.Event()
    ending = zenoh_named_thread(BURN_S, first_done)
    start = meter.read()
    assert start.zenoh_threads["cloud"][ending.native_id] >= BURN_S / 2, start
    first_done.set()
    ending.join()
    born = zenoh_named_thread(BURN_S, second_done)  # born in between: its whole life counts
    end = meter.read()
    second_done.set()
    born.join()
    used = meter.usage(start, end)
    assert ending.native_id not in end.zenoh_threads["cloud"]
    assert used["cloud_zenoh_cores"] >= 0, used
    assert used["cloud_zenoh_cores"] * (end.at - start.at) == pytest.approx(BURN_S, abs=0.05)


def test_an_unpinned_meter_does_not_claim_the_clouds_cpus() -> None:
    meter = CpuMeter({"generator": os.getpid()})
    start = meter.read()
    burn(BURN_S / 4)
    assert "others_on_cloud_cpus_cores" not in meter.usage(start, meter.read())
    with pytest.raises(ValueError, match="not one of the processes"):
        CpuMeter({"generator": os.getpid()}, cloud="cloud")


def record(
    latency_s: float, queue_s: float, compute_s: float, outcome: FrameOutcome
) -> FrameRecord:
    return FrameRecord("robot-1", 0, 0.0, latency_s, outcome, "edge-1", queue_s, compute_s)


def test_the_rest_of_a_frames_latency_is_outside_the_wait_and_the_run() -> None:
    served = [record(0.020 + i / 1000, 0.002, 0.010, FrameOutcome.SERVED) for i in range(20)]
    refused = [record(0.500, 0.0, 0.0, FrameOutcome.BUSY)]
    p95 = transport_p95_s(served + refused)
    assert p95 == pytest.approx(0.008 + 0.95 * 0.019)
    assert transport_p95_s(refused) is None


def phase(kind: str, p95_s: float, cores: float | None) -> dict[str, object]:
    row: dict[str, object] = {
        "phase": kind,
        "victim_p95_latency_s": p95_s,
        "victim_p95_queue_s": 0.001,
        "victim_p95_compute_s": 0.010,
        "victim_p95_transport_s": 0.002,
        "neighbour_sent_fps": 10.0 if kind == "polite" else 150.0,
        "neighbour_busy_rate": 0.0,
    }
    if cores is not None:
        row["cloud_cores"] = cores
    return row


def test_medians_per_figure_skip_missing_values() -> None:
    rows = [phase("hog", 0.02, 1.0), phase("hog", 0.04, None), phase("hog", 0.03, 0.8)]
    medians = phase_medians(rows)
    assert medians["victim_p95_latency_s"] == 0.03
    assert medians["cloud_cores"] == pytest.approx(0.9)  # the phase without one is left out


@pytest.mark.parametrize("pinned", [None, {"cloud": [1], "rest": [0]}])
def test_the_report_shows_both_settings_and_where_the_time_went(pinned: object) -> None:
    p95_s = {"polite": 0.01, "hog": 0.011}
    medians = {kind: phase_medians([phase(kind, p95_s[kind], None)]) for kind in KINDS}
    setting = {
        "batching": "off",
        "max_in_flight_per_robot": 1,
        "heavy_robots_low_priority": True,
        "polite_p95_s": 0.01,
        "hog_p95_s": 0.011,
        "ratio": 1.1,
        "pooled_ratio": 1.05,
        "hog_served_fps": 100.0,
        "hog_busy_rate": 0.36,
        "victim_busy_rate": 0.0,
        "victim_frames_per_phase": 30,
        "medians": medians,
    }
    settings = {
        "model": "zoo:resnet",
        "input_shape": [3, 240, 320],
        "fps_per_robot": 10.0,
        "workers": 2,
        "pin_cloud": pinned,
    }
    text = fairness_markdown({"load": "emulated", "settings": settings, "fairness": [setting]})
    assert "| off | 1 | yes | 0.0100 | 0.0110 | 1.10 | 1.05 | 100 | 36% | 0% |" in text
    assert "| 1 | yes | hog | 1.0 | 10.0 | 2.0 | 150 | n/a (n/a) |" in text
    assert ("pinned to CPU(s) 1" in text) == (pinned is not None)
