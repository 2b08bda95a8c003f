"""Providers (common.providers): the names a fleet file may use parse into typed values with the
known names in the error, onnxruntime's own names keep working, and a session that asked for an
accelerator and got the CPU is caught and named — never a silent fallback. Runs against the real
onnxruntime of this host (a CPU build: CUDAExecutionProvider is not in it)."""

from __future__ import annotations

import logging
from pathlib import Path

import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from common.config import BatchingConfig, load_fleet
from common.errors import UserError
from common.providers import (
    CPU_PROVIDER,
    ORT_PROVIDER_NAMES,
    ProviderFallback,
    ProviderName,
    ProviderSpec,
    check_list,
    check_session,
    cuda_ready,
    enforce,
    missing_reason,
    ort_providers,
    parse_provider,
    prepare,
)

CASES = Path(__file__).resolve().parents[1] / "config_cases"
CUDA = "CUDAExecutionProvider"
TRT = "TensorrtExecutionProvider"
cpu_only = pytest.mark.skipif(
    CUDA in ort.get_available_providers(), reason="this onnxruntime has CUDA (a GPU build)"
)
# onnxruntime's own warning when it drops a provider: the behaviour under test.
ORT_FALLBACK_WARNING = "ignore:Specified provider:UserWarning"


def test_short_names_and_onnxruntime_names_parse_to_the_same_value() -> None:
    assert parse_provider("cuda") == parse_provider(CUDA) == ProviderSpec(CUDA)
    assert parse_provider("cpu") == ProviderSpec(CPU_PROVIDER)
    assert parse_provider("tensorrt").short is ProviderName.TENSORRT
    assert parse_provider("cuda").gpu and parse_provider("tensorrt").gpu
    assert not parse_provider("cpu").gpu
    assert parse_provider("OpenVINOExecutionProvider").label == "OpenVINOExecutionProvider"


def test_every_provider_onnxruntime_knows_is_accepted() -> None:
    # Guards the contract "the onnxruntime names accepted before keep working": a newer
    # onnxruntime that knows more names fails here until they are added to ORT_PROVIDER_NAMES.
    missing = set(ort.get_all_providers()) - set(ORT_PROVIDER_NAMES)
    assert not missing, f"add to ORT_PROVIDER_NAMES: {sorted(missing)}"
    for name in ort.get_all_providers():
        assert parse_provider(name).ort_name == name


def test_options_become_onnxruntime_provider_options() -> None:
    trt = parse_provider(
        {"tensorrt": {"device_id": 1, "engine_cache": "/c/engines", "timing_cache": "/c/t"}}
    )
    cuda = parse_provider({"cuda": {"device_id": 1}})
    assert ort_providers([trt, cuda, parse_provider("cpu")]) == [
        (
            TRT,
            {
                "device_id": "1",
                "trt_engine_cache_enable": "True",
                "trt_engine_cache_path": "/c/engines",
                "trt_timing_cache_enable": "True",
                "trt_timing_cache_path": "/c/t",
            },
        ),
        (CUDA, {"device_id": "1"}),
        CPU_PROVIDER,
    ]
    # The fleet-file form reads back as the same value.
    assert parse_provider(trt.to_config()) == trt
    assert parse_provider(cuda.to_config()) == cuda
    assert parse_provider("cpu").to_config() == "cpu"


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ("gpu", "unknown provider 'gpu'; known: cpu, cuda, tensorrt"),
        ({"cuda": {"devce_id": 0}}, "cuda: unknown option(s) devce_id; options: device_id"),
        ({"cpu": {"device_id": 0}}, "cpu: unknown option(s) device_id; options: none"),
        ({"cuda": {"device_id": -1}}, "device_id must be an integer >= 0"),
        ({"cuda": {"device_id": True}}, "device_id must be an integer >= 0"),
        ({"tensorrt": {"engine_cache": ""}}, "engine_cache must be a folder path"),
        ({"cuda": 0}, "cuda: options must be a mapping"),
        ({"cuda": {}, "cpu": {}}, "is not a provider"),
        (3, "is not a provider"),
    ],
)
def test_a_bad_entry_is_named_with_what_is_known(entry: object, words: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_provider(entry)
    assert words in str(info.value)


def test_a_provider_listed_twice_is_refused() -> None:
    with pytest.raises(ValueError, match="cuda is listed twice"):
        check_list([parse_provider("cuda"), parse_provider(CUDA)])


def _session(providers: list[object]) -> ort.InferenceSession:
    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["y"])],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])],
    )
    # IR 8: what every onnxruntime of the locks reads (a newer onnx writes a newer IR by default).
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    options = ort.SessionOptions()
    options.log_severity_level = 3  # onnxruntime's own fallback warning is what is tested here
    return ort.InferenceSession(model.SerializeToString(), options, providers=providers)


@cpu_only
@pytest.mark.filterwarnings(ORT_FALLBACK_WARNING)
def test_onnxruntime_falls_back_silently_and_the_check_names_why() -> None:
    specs = [parse_provider("cuda"), parse_provider("cpu")]
    session = _session(ort_providers(specs))  # no error from onnxruntime itself
    assert session.get_providers() == [CPU_PROVIDER]
    check = check_session(session, specs)
    assert check.fell_back
    assert check.got == (CPU_PROVIDER,)
    ((name, reason),) = check.missing
    assert name == CUDA
    assert f"{CUDA} is not in this onnxruntime build" in reason
    assert "CPUExecutionProvider" in reason  # what the build has
    assert "onnxruntime-gpu" in reason
    assert reason == missing_reason(specs[0])


def test_a_session_that_got_what_it_asked_for_passes() -> None:
    specs = [parse_provider("cpu")]
    check = check_session(_session(ort_providers(specs)), specs)
    assert not check.fell_back and check.got == (CPU_PROVIDER,)


@cpu_only
def test_refuse_is_one_named_line_and_allow_is_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    specs = [parse_provider("cuda"), parse_provider("cpu")]
    sessions = {"suffix of cut 0": [CPU_PROVIDER]}
    with pytest.raises(UserError) as info:
        enforce(sessions, specs, ProviderFallback.REFUSE, who="edge-1")
    message = str(info.value)
    assert message.startswith("edge-1: suffix of cut 0: asked for CUDAExecutionProvider")
    assert f"{CUDA} is not in this onnxruntime build" in message
    assert "providers_fallback: allow" in message
    assert "\n" not in message
    with caplog.at_level(logging.WARNING, logger="common.providers"):
        check = enforce(sessions, specs, ProviderFallback.ALLOW, who="edge-1")
    assert check.fell_back and check.got == (CPU_PROVIDER,)
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "serving on CPUExecutionProvider (providers_fallback: allow)" in caplog.text


def test_the_fleet_file_form_of_a_gpu_deployment() -> None:
    config = load_fleet(CASES / "valid-gpu-providers.yaml")
    gpu1, gpu2, edge = (config.machine(m) for m in ("gpu-1", "gpu-2", "edge-1"))
    assert [p.label for p in gpu1.providers] == ["tensorrt", "cuda", "cpu"]
    # Cache folders are relative to the fleet file, like every path in it.
    assert gpu1.providers[0].engine_cache == str(CASES / "trt" / "engines")
    assert gpu1.providers_fallback is ProviderFallback.REFUSE
    assert gpu2.providers_fallback is ProviderFallback.ALLOW
    # gpu_serving 'auto' follows the first provider; YAML's bare `off` is the word 'off'.
    assert gpu1.gpu_serving_on and edge.gpu_serving_on and not gpu2.gpu_serving_on
    assert not config.machine("robot-1").gpu_serving_on
    assert gpu1.batching.bucket_sizes == (1, 4, 8, 16)
    assert [p.ort_name for p in edge.providers] == [CUDA, CPU_PROVIDER]


@pytest.mark.parametrize(
    ("sizes", "buckets"),
    [
        ([8], (1, 2, 4, 8)),
        ([16], (1, 2, 4, 8, 16)),
        ([6], (1, 2, 4, 6)),
        ([3, 12], (1, 2, 3, 4, 8, 12)),
    ],
)
def test_default_buckets_are_powers_of_two_and_the_preferred_sizes(
    sizes: list[int], buckets: tuple[int, ...]
) -> None:
    batching = BatchingConfig(enabled=True, preferred_batch_sizes=sizes)
    assert batching.bucket_sizes == buckets
    assert BatchingConfig(enabled=False).bucket_sizes == (1,)
    # Buckets past the one that holds the largest batch are never formed.
    assert BatchingConfig(
        enabled=True, preferred_batch_sizes=[5], buckets=[8, 16, 32]
    ).bucket_sizes == (1, 8)


gpu_only = pytest.mark.skipif(
    not cuda_ready(), reason="needs onnxruntime-gpu, its CUDA libraries and a GPU"
)
gpu_build_without_gpu = pytest.mark.skipif(
    CUDA not in ort.get_available_providers() or cuda_ready(),
    reason="needs onnxruntime-gpu on a host where CUDA cannot run",
)


@gpu_build_without_gpu
@pytest.mark.filterwarnings(ORT_FALLBACK_WARNING)
def test_a_gpu_build_without_cuda_libraries_or_gpu_names_what_is_missing() -> None:
    # `pip install elasticfog[gpu]` on a CPU host: CUDAExecutionProvider is in the build, its
    # library does not load (the loader names the first CUDA library missing) or the driver
    # sees no GPU; onnxruntime still falls back to the CPU without raising.
    specs = [parse_provider("cuda"), parse_provider("cpu")]
    prepare(specs)
    check = check_session(_session(ort_providers(specs)), specs)
    assert check.fell_back and check.got == (CPU_PROVIDER,)
    ((_, reason),) = check.missing
    assert reason.startswith(f"{CUDA}: ")
    assert (
        "libonnxruntime_providers_cuda.so does not load: lib" in reason
        or "NVIDIA driver" in reason
        or "GPU(s) visible" in reason
    ), reason


@gpu_only
def test_on_a_gpu_machine_a_cuda_session_gets_cuda() -> None:
    # Runs where onnxruntime-gpu is installed (benchmarks/gpu_device_run.sh runs this file);
    # on a GPU build without a usable GPU it fails with the reason the check names.
    specs = [parse_provider("cuda"), parse_provider("cpu")]
    prepare(specs)
    check = check_session(_session(ort_providers(specs)), specs)
    assert not check.fell_back, check.message()
    assert check.got[0] == CUDA
