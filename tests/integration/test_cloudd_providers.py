"""The cloud daemon's providers and gpu_serving, on this CPU host (a CPU build of onnxruntime,
where CUDAExecutionProvider does not exist): asking for CUDA stops `elasticfog cloud` at start
with one line naming the missing provider, never serving from the CPU unnoticed; with
`providers_fallback: allow` it serves on the CPU and its probe reply says so; the robot daemon
checks its sessions the same way. With `gpu_serving: on` and batching, every bucket is warmed at
start and results are the model's."""

from __future__ import annotations

import subprocess
import uuid
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import yaml

from common.partition import sample_feeds
from common.partition.runtime import SplitModel
from common.providers import cuda_ready
from common.wire.cloud_to_robot import InferReply
from deploy.procs import elasticfog_argv
from tests.integration.test_cloudd import (  # noqa: F401  (fixtures used by name)
    ask_one,
    connect,
    infer_request,
    probe,
    reference,
    serve,
    start_cloud,
    svc_key,
    tiny_path,
)
from tests.unit.test_cloudd_validate import write_tiny_model

CUDA = "CUDAExecutionProvider"
EXIT_WITHIN_S = 60.0
RESULT_ATOL = 1e-4
USER_ERROR_EXIT = 2

pytestmark = [
    pytest.mark.skipif(cuda_ready(), reason="CUDA runs here: nothing falls back"),
    # onnxruntime's own warning when it drops CUDA for the CPU: the behaviour under test.
    pytest.mark.filterwarnings("ignore:Specified provider:UserWarning"),
]


def test_asking_for_cuda_stops_the_daemon_at_start_naming_the_provider(tmp_path: Path) -> None:
    model = write_tiny_model(tmp_path / "tiny.onnx")
    # Nothing listens there: the daemon must stop before it tries to connect.
    endpoint = "tcp/127.0.0.1:9"
    data = {
        "fleet": f"gpu-{uuid.uuid4().hex[:8]}",
        "service": "vision",
        "model": str(model),
        "registry": {"endpoint": endpoint, "listen": [endpoint]},
        "machines": {
            "edge-1": {"role": "cloud", "providers": ["cuda", "cpu"]},
            "robot-1": {"role": "robot"},
        },
        "initial_policy": {"edge-1": "service"},
        "latency_bound": {"seconds": 0.5},
        "deadline_s": 1.0,
    }
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text(yaml.safe_dump(data), encoding="utf-8")
    done = subprocess.run(
        [*elasticfog_argv(), "cloud", "--config", str(fleet), "--id", "edge-1"],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=EXIT_WITHIN_S,
        check=False,
    )
    assert done.returncode == USER_ERROR_EXIT, done.stdout + done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, done.stderr
    assert (
        f"edge-1: suffix of cut 0: asked for {CUDA}, CPUExecutionProvider but the session runs "
        f"on CPUExecutionProvider: {CUDA}" in errors[0]
    )
    if CUDA not in ort.get_available_providers():  # the CPU build: the cure is the GPU one
        assert f"{CUDA} is not in this onnxruntime build" in errors[0]
        assert "onnxruntime-gpu" in errors[0]
    else:  # onnxruntime-gpu on a host without CUDA: the library or the driver, named
        assert "does not load: lib" in errors[0] or "NVIDIA driver" in errors[0], errors[0]


def test_fallback_allowed_serves_on_the_cpu_and_says_so(
    start_cloud,  # noqa: F811
    open_peer,
    wait_for_token,
    reference: SplitModel,  # noqa: F811
    caplog: pytest.LogCaptureFixture,
) -> None:
    daemon = start_cloud(providers=["cuda", "cpu"], providers_fallback="allow")
    assert daemon.providers is not None and daemon.providers.fell_back
    assert f"asked for {CUDA}, CPUExecutionProvider but the session runs on" in caplog.text
    session = connect(open_peer, daemon, wait_for_token)
    reply = probe(session, daemon)
    assert reply.providers == ("CPUExecutionProvider",)
    assert reply.providers_fallback is True
    serve(session, daemon, reference)
    feeds = sample_feeds(reference.input_specs(), seed=5)
    answer = ask_one(session, svc_key(daemon), infer_request(reference, 1, 7, feeds).to_wire())
    assert isinstance(answer, InferReply), answer
    for name, value in reference.run_full(feeds).items():
        np.testing.assert_allclose(answer.outputs[name], value, atol=RESULT_ATOL)


def test_a_cpu_deployment_reports_its_providers_without_a_fallback(
    start_cloud,  # noqa: F811
    open_peer,
    wait_for_token,
) -> None:
    daemon = start_cloud()
    reply = probe(connect(open_peer, daemon, wait_for_token), daemon)
    assert reply.providers == ("CPUExecutionProvider",)
    assert reply.providers_fallback is False


def test_gpu_serving_warms_every_bucket_and_serves_the_models_results(
    start_cloud,  # noqa: F811
    open_peer,
    wait_for_token,
    reference: SplitModel,  # noqa: F811
) -> None:
    daemon = start_cloud(
        gpu_serving="on",
        batching={"enabled": True, "preferred_batch_sizes": [4], "buckets": [2, 4]},
    )
    model = daemon.model
    assert model.io_binding and model.buckets == (1, 2, 4)
    batched = [k for k in range(model.num_cuts) if model.batched(k)]
    assert batched, "the tiny model takes a batch at some cut"
    assert model.warmed == {k: (1, 2, 4) for k in batched}
    session = connect(open_peer, daemon, wait_for_token)
    serve(session, daemon, reference)
    feeds = sample_feeds(reference.input_specs(), seed=9)
    full = reference.run_full(feeds)
    for cut in range(reference.num_cuts):
        request = infer_request(reference, cut, frame=200 + cut, feeds=feeds)
        answer = ask_one(session, svc_key(daemon), request.to_wire())
        assert isinstance(answer, InferReply), answer
        for name, value in full.items():
            np.testing.assert_allclose(answer.outputs[name], value, atol=RESULT_ATOL)


def test_the_robot_refuses_a_cuda_fallback_too_unless_allowed(tiny_path: Path) -> None:  # noqa: F811
    from common.config import FleetConfig, fleet_from_dict
    from common.errors import UserError
    from robotd.robot_model import open_split_model

    def fleet(**robot: object) -> FleetConfig:
        return fleet_from_dict(
            {
                "service": "vision",
                "model": str(tiny_path),
                "machines": {
                    "edge-1": {"role": "cloud"},
                    "robot-1": {"role": "robot", "providers": ["cuda", "cpu"], **robot},
                },
                "initial_policy": {"edge-1": "service"},
                "latency_bound": {"seconds": 0.5},
                "deadline_s": 1.0,
            }
        )

    cfg = fleet()
    with pytest.raises(UserError, match=f"robot-1: the full model: asked for {CUDA}"):
        open_split_model(cfg, cfg.machine("robot-1"), who="robot-1")
    allowed = fleet(providers_fallback="allow")
    with open_split_model(allowed, allowed.machine("robot-1"), who="robot-1") as model:
        assert set(model.session_providers()["the full model"]) == {"CPUExecutionProvider"}
