"""benchmarks/gpu_suffix.py on this CPU host, briefly: the CPU rows carry times and served
frames, the GPU rows are skipped with the reason the daemon's own check names (a CPU build of
onnxruntime has no CUDAExecutionProvider), and the JSON holds the figures docs/scale.md asks for."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import onnxruntime as ort
import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_suffix.py"
CUDA = "CUDAExecutionProvider"


def _bench() -> ModuleType:
    """The benchmark's module, loaded from its file (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("gpu_suffix", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while being made
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(CUDA in ort.get_available_providers(), reason="a GPU build of onnxruntime")
def test_cpu_rows_measured_and_gpu_rows_skipped_with_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bench.json"
    code = _bench().main(
        [
            "--models", "zoo:mobilenet", "--input-shape", "3x32x32",
            "--providers", "cpu,cuda", "--rounds", "2", "--robots", "4",
            "--duration-s", "0.5", "--workers", "2", "--out", str(out),
        ]
    )  # fmt: skip
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text(encoding="utf-8"))
    assert printed["host"]["available_providers"] == ort.get_available_providers()
    (model,) = printed["models"]
    assert model["model"] == "zoo:mobilenet" and model["cut_tensors"] == ["input"]
    cpu = [r for r in model["suffix"] if r["provider"] == "cpu"]
    assert [r["batch"] for r in cpu] == [1, 8, 16]
    assert all(r["ms_per_frame_median"] > 0 for r in cpu)
    (cuda,) = [r for r in model["suffix"] if r["provider"] == "cuda"]
    assert f"{CUDA} is not in this onnxruntime build" in cuda["skipped"]
    cells = {(r["provider"], r["mode"]): r for r in model["serving"] if "mode" in r}
    assert set(cells) == {("cpu", "batch1"), ("cpu", "batcher")}
    assert all(c["frames"] > 0 and c["errors"] == [] for c in cells.values())
    assert cells[("cpu", "batch1")]["largest_batch"] == 1
    assert next(r for r in model["serving"] if r["provider"] == "cuda")["skipped"]
    (gain,) = model["summary"]["batching"]
    assert gain["provider"] == "cpu" and gain["robots"] == 4 and gain["fps_gain"] > 0
    assert model["summary"]["suffix_ms_batch1"]["cpu"] > 0
