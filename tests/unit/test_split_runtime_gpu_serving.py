"""gpu_serving's parts of SplitModel, on the CPU: IO binding gives the results of a plain run,
a batched run padded up to its bucket gives each item the rows of its own run (the padding's
rows dropped), and warm-up runs every bucket the batcher can form."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.partition import Partition, sample_feeds, split_model
from common.partition.runtime import SplitModel
from common.providers import cuda_ready, ort_providers, parse_provider, prepare
from tests.unit.test_partition import matmul_chain, save
from tests.unit.test_split_runtime_batch import items_for

BUCKETS = (1, 2, 4, 8)
GPU_RTOL = 1e-3
"""A GPU's kernels sum in another order (and may use TF32): close to the CPU's, not equal."""


@pytest.fixture
def split(tmp_path: Path) -> Partition:
    return split_model(
        save(matmul_chain(4, 256, out_dim=10), tmp_path / "m.onnx"), tmp_path / "split"
    )


def open_model(split: Partition, **options: Any) -> SplitModel:
    return SplitModel(split, lazy=True, **options)


def test_io_binding_gives_the_results_of_a_plain_run(split: Partition) -> None:
    plain = open_model(split)
    bound = open_model(split, io_binding=True)
    feeds = sample_feeds(plain.input_specs(), seed=3)
    np.testing.assert_array_equal(bound.run_full(feeds)["y"], plain.run_full(feeds)["y"])
    for k in range(plain.num_cuts):
        tensors = plain.run_prefix(k, feeds)
        assert {n: v.shape for n, v in bound.run_prefix(k, feeds).items()} == {
            n: v.shape for n, v in tensors.items()
        }
        np.testing.assert_array_equal(
            bound.run_suffix(k, tensors)["y"], plain.run_suffix(k, tensors)["y"]
        )
    # Batched and bound together.
    assert plain.enable_batching(0) is None and bound.enable_batching(0) is None
    items = items_for(plain, 0, 3)
    for mine, theirs in zip(
        bound.run_suffix_batch(0, items), plain.run_suffix_batch(0, items), strict=True
    ):
        np.testing.assert_array_equal(mine["y"], theirs["y"])


@pytest.mark.parametrize("count", [2, 3, 5, 8])
def test_a_batch_padded_to_its_bucket_gives_each_item_its_own_rows(
    split: Partition, count: int
) -> None:
    model = open_model(split, buckets=BUCKETS, io_binding=True)
    assert model.bucket_for(count) == next(b for b in BUCKETS if b >= count)
    for k in range(model.num_cuts):
        items = items_for(model, k, count)
        alone = [model.run_suffix(k, item) for item in items]
        assert model.enable_batching(k) is None
        together = model.run_suffix_batch(k, items)
        assert len(together) == count  # the padding's rows are dropped
        for mine, batched in zip(alone, together, strict=True):
            assert batched["y"].shape == mine["y"].shape == (1, 10)
            np.testing.assert_allclose(batched["y"], mine["y"], rtol=1e-5, atol=1e-5)


def test_sizes_past_the_largest_bucket_run_unpadded(split: Partition) -> None:
    model = open_model(split, buckets=(4,))
    assert model.buckets == (1, 4)  # one item always runs alone
    assert [model.bucket_for(n) for n in (1, 2, 4, 6)] == [1, 4, 4, 6]
    with pytest.raises(ValueError, match="buckets must be sizes >= 1"):
        open_model(split, buckets=(0, 4))


def test_warm_up_runs_every_bucket_of_every_batched_cut(split: Partition) -> None:
    model = open_model(split, buckets=BUCKETS)
    with pytest.raises(ValueError, match="enable_batching first"):
        model.warm_batches(0, BUCKETS)
    for k in range(model.num_cuts):
        assert model.enable_batching(k) is None
        model.warm_batches(k, BUCKETS)
    assert model.warmed == {k: BUCKETS for k in range(model.num_cuts)}
    # Sizes between buckets are run as their bucket: warming 1..8 meets the same shapes.
    other = open_model(split, buckets=BUCKETS)
    assert other.enable_batching(0) is None
    other.warm_batches(0, range(1, 9))
    assert other.warmed[0] == BUCKETS


def test_session_providers_report_what_each_session_got(split: Partition) -> None:
    model = open_model(split)
    assert model.session_providers() == {}
    model.run_suffix(0, model.run_prefix(0, sample_feeds(model.input_specs())))
    assert model.suffix_providers(0) == ["CPUExecutionProvider"]
    assert model.session_providers() == {"suffix of cut 0": ["CPUExecutionProvider"]}


@pytest.mark.skipif(not cuda_ready(), reason="needs onnxruntime-gpu, its CUDA libraries and a GPU")
def test_on_a_gpu_io_binding_and_buckets_give_the_cpus_results(split: Partition) -> None:
    # Runs where onnxruntime-gpu is installed (benchmarks/gpu_device_run.sh runs this file).
    specs = [parse_provider("cuda"), parse_provider("cpu")]
    prepare(specs)
    cpu = open_model(split)
    gpu = open_model(split, providers=ort_providers(specs), io_binding=True, buckets=BUCKETS)
    for k in range(cpu.num_cuts):
        items = items_for(cpu, k, 3)
        assert gpu.enable_batching(k) is None
        assert gpu.suffix_providers(k)[0] == "CUDAExecutionProvider"
        gpu.warm_batches(k, BUCKETS)
        for mine, theirs in zip(gpu.run_suffix_batch(k, items), items, strict=True):
            want = cpu.run_suffix(k, theirs)["y"]
            np.testing.assert_allclose(mine["y"], want, rtol=GPU_RTOL, atol=GPU_RTOL)
