"""SplitModel: running prefixes and suffixes, its errors, and one shared copy of the weights."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.partition import sample_feeds, split_model
from common.partition.runtime import SplitModel
from tests.helpers.onnx_graphs import diamond, late_input, matmul_chain, save, two_outputs

# A 15-layer MatMul chain has 16 cuts (the inputs, after each ReLU, before the final Identity);
# each layer's weights are 640x640 float32 (1.6 MB).
RSS_CUTS = 16
RSS_LAYERS = RSS_CUTS - 1
RSS_DIM = 640
RSS_MAX_RATIO = 1.5


@pytest.fixture
def runtime(tmp_path: Path) -> SplitModel:
    return SplitModel(split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split"))


def test_every_cut_reproduces_the_full_model(runtime: SplitModel) -> None:
    feeds = sample_feeds(runtime.input_specs(), seed=7)
    full = runtime.run_full(feeds)
    assert list(full) == ["y"]
    for k in range(runtime.num_cuts):
        sent = runtime.run_prefix(k, feeds)
        assert list(sent) == runtime.partition.cuts[k].tensors
        np.testing.assert_allclose(runtime.run_suffix(k, sent)["y"], full["y"], atol=1e-6)


def test_cut_zero_sends_the_inputs_as_they_are(runtime: SplitModel) -> None:
    feeds = sample_feeds(runtime.input_specs())
    sent = runtime.run_prefix(0, feeds)
    assert list(sent) == ["x"]
    assert sent["x"] is feeds["x"] or np.array_equal(sent["x"], feeds["x"])


def test_cut_tensor_specs_describe_what_the_prefix_sends(runtime: SplitModel) -> None:
    feeds = sample_feeds(runtime.input_specs())
    for k in range(runtime.num_cuts):
        sent = runtime.run_prefix(k, feeds)
        specs = runtime.cut_tensor_specs(k)
        assert [s.name for s in specs] == list(sent)
        for spec in specs:
            assert (spec.dtype, spec.shape) == (sent[spec.name].dtype.name, sent[spec.name].shape)
            assert spec.nbytes == sent[spec.name].nbytes


def test_missing_cut_tensor_is_named(runtime: SplitModel) -> None:
    with pytest.raises(ValueError, match=r"suffix of cut 2: missing tensor\(s\) b"):
        runtime.run_suffix(2, {"a": np.zeros((1, 4), np.float32)})


def test_unknown_cut_index(runtime: SplitModel) -> None:
    with pytest.raises(ValueError, match=r"unknown cut 9: this model has cuts 0\.\.3"):
        runtime.run_prefix(9, {})


def test_late_input_can_come_from_the_original_feeds(tmp_path: Path) -> None:
    rt = SplitModel(split_model(save(late_input(), tmp_path / "m.onnx"), tmp_path / "s"))
    feeds = sample_feeds(rt.input_specs())
    full = rt.run_full(feeds)["y"]
    sent = rt.run_prefix(2, feeds)
    assert list(sent) == ["z", "b"]
    only_b = {"b": sent["b"]}
    np.testing.assert_array_equal(rt.run_suffix(2, only_b, feeds=feeds)["y"], full)


def test_early_output_passes_through_the_suffix(tmp_path: Path) -> None:
    rt = SplitModel(split_model(save(two_outputs(), tmp_path / "m.onnx"), tmp_path / "s"))
    feeds = sample_feeds(rt.input_specs())
    full = rt.run_full(feeds)
    out = rt.run_suffix(3, rt.run_prefix(3, feeds))
    assert list(out) == ["y1", "y2"]
    for name in out:
        np.testing.assert_array_equal(out[name], full[name])


def test_weight_bytes_counts_each_weight_once(tmp_path: Path) -> None:
    model = matmul_chain(3, 32)
    expected = sum(np.prod(t.dims) * 4 for t in model.graph.initializer)
    rt = SplitModel(split_model(save(model, tmp_path / "m.onnx"), tmp_path / "s"))
    assert rt.weight_bytes == expected
    # the sub-model files reference weights.bin instead of holding copies
    sizes = [p.stat().st_size for p in (tmp_path / "s").glob("cut*.onnx")]
    assert max(sizes) < expected / 4


def test_lazy_sessions_are_built_on_first_use(tmp_path: Path) -> None:
    part = split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "s")
    rt = SplitModel(part, lazy=True, threads=1)
    assert not rt._suffix
    rt.run_suffix(1, rt.run_prefix(1, sample_feeds(rt.input_specs())))
    assert list(rt._suffix) == [1]


# onnxruntime's first session and first run cost about 11 MB once per process (environment,
# kernel registry, thread pool) whatever the model; a warm-up session takes that out of the figure.
_RSS_PROBE = """
import json, sys
import numpy as np, onnx, onnxruntime as ort, psutil
from onnx import TensorProto, helper
from common.partition import Partition, sample_feeds
from common.partition.runtime import SplitModel
x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])
y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4])
g = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "warm", [x], [y])
warm = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], ir_version=10)
opts = ort.SessionOptions()
opts.intra_op_num_threads = 1
ort.InferenceSession(warm.SerializeToString(), opts).run(None, {"x": np.ones((1, 4), np.float32)})
part = Partition.load(sys.argv[1])
proc = psutil.Process()
before = proc.memory_info().rss
rt = SplitModel(part, threads=1)
feeds = sample_feeds(rt.input_specs())
for k in range(rt.num_cuts):
    rt.run_suffix(k, rt.run_prefix(k, feeds))
rt.run_full(feeds)
after = proc.memory_info().rss
print(json.dumps({"cuts": rt.num_cuts, "weights": rt.weight_bytes, "rss": after - before}))
"""


def test_sixteen_cuts_share_one_copy_of_the_weights(tmp_path: Path) -> None:
    """Regression guard: 32 sessions (full + 15 prefixes + 16 suffixes) must not hold 32 copies.

    Measured in a fresh interpreter so the split's own allocations do not blur the figure.
    """
    model = matmul_chain(RSS_LAYERS, RSS_DIM)
    part = split_model(save(model, tmp_path / "m.onnx"), tmp_path / "s")
    assert len(part.cuts) == RSS_CUTS
    done = subprocess.run(
        [sys.executable, "-c", _RSS_PROBE, str(part.dir)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    figures = json.loads(done.stdout)
    ratio = figures["rss"] / figures["weights"]
    assert figures["weights"] == RSS_LAYERS * RSS_DIM * RSS_DIM * 4
    assert ratio <= RSS_MAX_RATIO, f"resident memory is {ratio:.2f}x the weights: {figures}"
