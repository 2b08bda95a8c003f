"""The speculative local run of a hedged frame (`robotd.frame_path.local_runs.LocalRunner`), on real
onnxruntime sessions: it runs on a thread of the lowest CPU priority (the caller's stays as it
was), a cancelled run stops within a node instead of running to its end, a queued one never
starts, and a failure is handed back instead of killing the thread.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from common.partition import sample_feeds, split_model
from common.partition.runtime import SplitModel
from robotd.frame_path.local_runs import SPECULATIVE_NICE, LocalRunner
from tests.helpers.onnx_graphs import diamond, make_model, save

WAIT_S = 10.0
SIZE = 256
LAYERS = 300


def slow_session(tmp_path: Path) -> ort.InferenceSession:
    """x[SIZE,SIZE] → LAYERS chained MatMuls: tens of ms a run, a node boundary every ~0.1 ms."""
    rng = np.random.default_rng(0)
    weight = numpy_helper.from_array(
        (rng.standard_normal((SIZE, SIZE)) / SIZE).astype(np.float32), "w"
    )
    nodes = []
    prev = "x"
    for i in range(LAYERS):
        out = "y" if i == LAYERS - 1 else f"h{i}"
        nodes.append(helper.make_node("MatMul", [prev, "w"], [out]))
        prev = out
    model = make_model(
        nodes,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [SIZE, SIZE])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [SIZE, SIZE])],
        [weight],
    )
    path = save(model, tmp_path / "chain.onnx")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@pytest.fixture
def runner() -> Iterator[LocalRunner]:
    r = LocalRunner("test-local-run")
    r.start()
    yield r
    r.stop()


def feeds() -> dict[str, np.ndarray]:
    return {"x": np.ones((SIZE, SIZE), dtype=np.float32)}


def test_the_run_gets_the_lowest_priority_and_the_caller_keeps_its_own(
    runner: LocalRunner,
) -> None:
    if not sys.platform.startswith("linux"):
        pytest.skip("per-thread nice values are a Linux feature")
    seen: dict[str, int] = {}

    def probe(options: ort.RunOptions) -> dict[str, np.ndarray]:
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        return {}

    before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    job = runner.submit(probe)
    assert job.wait(WAIT_S)
    assert runner.niced
    assert seen["nice"] == SPECULATIVE_NICE
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before


def test_a_completed_run_gives_its_outputs_and_time(runner: LocalRunner, tmp_path: Path) -> None:
    session = slow_session(tmp_path)
    wake = threading.Event()
    job = runner.submit(lambda options: {"y": session.run(None, feeds(), options)[0]}, wake)
    assert wake.wait(WAIT_S) and job.done and job.completed
    assert job.outputs is not None and job.outputs["y"].shape == (SIZE, SIZE)
    assert job.elapsed_s is not None and job.elapsed_s > 0
    assert job.error is None


def test_a_cancelled_run_stops_long_before_its_end(runner: LocalRunner, tmp_path: Path) -> None:
    session = slow_session(tmp_path)
    t = time.perf_counter()
    session.run(None, feeds())
    full_s = time.perf_counter() - t
    started = threading.Event()

    def run(options: ort.RunOptions) -> dict[str, np.ndarray]:
        started.set()
        return {"y": session.run(None, feeds(), options)[0]}

    job = runner.submit(run)
    assert started.wait(WAIT_S)
    cancelled_at = time.perf_counter()
    job.cancel()
    assert job.wait(WAIT_S)
    stopped_s = time.perf_counter() - cancelled_at
    # Stopped at the next node: a small share of a whole run (measured here ~1 ms of ~40 ms).
    assert stopped_s < max(0.5 * full_s, 0.01), (stopped_s, full_s)
    assert job.outputs is None and job.error is None and not job.completed
    assert job.elapsed_s is None


def test_a_job_cancelled_while_queued_never_runs(runner: LocalRunner) -> None:
    gate = threading.Event()
    ran: list[str] = []

    def first_run(options: ort.RunOptions) -> dict[str, np.ndarray]:
        ran.append("first")
        gate.wait(WAIT_S)
        return {}

    def second_run(options: ort.RunOptions) -> dict[str, np.ndarray]:
        ran.append("second")
        return {}

    first = runner.submit(first_run)
    second = runner.submit(second_run)
    second.cancel()
    gate.set()
    assert first.wait(WAIT_S) and second.wait(WAIT_S)
    assert ran == ["first"]
    assert not second.completed


def test_a_failing_run_hands_back_its_error_and_the_runner_goes_on(runner: LocalRunner) -> None:
    def boom(options: ort.RunOptions) -> dict[str, np.ndarray]:
        raise ValueError("suffix of cut 3: missing tensor(s) t")

    failed = runner.submit(boom)
    assert failed.wait(WAIT_S)
    assert isinstance(failed.error, ValueError) and failed.outputs is None
    ok = runner.submit(lambda options: {"y": np.zeros(1)})
    assert ok.wait(WAIT_S) and ok.completed


def test_split_model_runs_take_run_options(tmp_path: Path) -> None:
    model = SplitModel(split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split"))
    x = sample_feeds(model.input_specs(), seed=1)
    options = ort.RunOptions()
    full = model.run_full(x, run_options=options)
    sent = model.run_prefix(1, x, run_options=options)
    suffix = model.run_suffix(1, sent, x, run_options=options)
    np.testing.assert_allclose(suffix["y"], full["y"], atol=1e-6)
    options.terminate = True  # what LocalJob.cancel() sets
    with pytest.raises(Exception, match="terminate"):
        model.run_full(x, run_options=options)


def test_stop_cancels_what_runs_and_ends_the_thread(tmp_path: Path) -> None:
    session = slow_session(tmp_path)
    r = LocalRunner("test-local-run-stop")
    r.start()
    started = threading.Event()

    def run(options: ort.RunOptions) -> dict[str, np.ndarray]:
        started.set()
        for _ in range(100):  # far longer than the stop's bound, unless cancelled
            session.run(None, feeds(), options)
        return {}

    job = r.submit(run)
    assert started.wait(WAIT_S)
    r.stop(timeout_s=WAIT_S)
    assert job.done and not job.completed
    with pytest.raises(RuntimeError, match="not running"):
        r.submit(lambda options: {})
