"""Batched suffixes (SplitModel.enable_batching): the batch axis is made symbolic in memory, the
weights stay shared, each item of a batch gets its own rows and equals its own run, and a suffix
that cannot take a batch says why and keeps serving one item at a time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from common.partition import sample_feeds, split_model
from common.partition.runtime import BATCH_DIM, NotBatchable, SplitModel, batch_axis_model
from tests.helpers.onnx_graphs import make_model, matmul_chain, node, save, vi

CHAIN_LAYERS = 4
CHAIN_DIM = 256  # weights big enough to live in the split's shared weights file
ITEMS = 5


@pytest.fixture
def chain(tmp_path: Path) -> SplitModel:
    model = matmul_chain(CHAIN_LAYERS, CHAIN_DIM, out_dim=10)
    return SplitModel(split_model(save(model, tmp_path / "m.onnx"), tmp_path / "split"))


def items_for(model: SplitModel, k: int, count: int = ITEMS) -> list[dict[str, np.ndarray]]:
    """Different frames' tensors at cut k."""
    return [
        model.run_prefix(k, sample_feeds(model.input_specs(), seed=100 + i)) for i in range(count)
    ]


def test_every_cut_of_a_chain_takes_a_batch_and_each_item_gets_its_own_result(
    chain: SplitModel,
) -> None:
    for k in range(chain.num_cuts):
        items = items_for(chain, k)
        alone = [chain.run_suffix(k, item) for item in items]
        assert chain.enable_batching(k) is None
        assert chain.batched(k)
        together = chain.run_suffix_batch(k, items)
        assert len(together) == ITEMS
        for mine, batched in zip(alone, together, strict=True):
            assert batched["y"].shape == mine["y"].shape == (1, 10)
            np.testing.assert_allclose(batched["y"], mine["y"], rtol=1e-5, atol=1e-5)
        # Different frames, different results: a mixed-up slice would be caught above.
        assert not np.allclose(together[0]["y"], together[1]["y"])
        # The batched session serves single requests too.
        np.testing.assert_allclose(chain.run_suffix(k, items[0])["y"], alone[0]["y"], atol=1e-5)


def test_a_batched_suffix_refuses_an_item_of_the_wrong_size(chain: SplitModel) -> None:
    assert chain.enable_batching(0) is None
    good = items_for(chain, 0, 1)[0]
    twice = {"x": np.concatenate([good["x"], good["x"]])}
    with pytest.raises(ValueError, match=r"x must have 1 row\(s\) on axis 0"):
        chain.run_suffix_batch(0, [good, twice])


def test_a_suffix_not_enabled_runs_item_by_item(chain: SplitModel) -> None:
    items = items_for(chain, 1, 3)
    assert not chain.batched(1)
    out = chain.run_suffix_batch(1, items)
    for item, result in zip(items, out, strict=True):
        np.testing.assert_array_equal(result["y"], chain.run_suffix(1, item)["y"])


def hard_coded_batch() -> onnx.ModelProto:
    """x[1,4] -> Reshape to a constant [1, 4] -> MatMul -> y[1,3]: a batch of two cannot pass
    the Reshape (what a model exported with `view(1, -1)` does)."""
    shape = numpy_helper.from_array(np.array([1, 4], np.int64), "shape")
    w = numpy_helper.from_array(np.ones((4, 3), np.float32), "W")
    return make_model(
        [node("Reshape", ["x", "shape"], ["r"]), node("MatMul", ["r", "W"], ["y"])],
        [vi("x", [1, 4])],
        [vi("y", [1, 3])],
        [shape, w],
    )


def test_a_hard_coded_batch_of_one_is_refused_with_the_reason(tmp_path: Path) -> None:
    model = SplitModel(split_model(save(hard_coded_batch(), tmp_path / "m.onnx"), tmp_path / "s"))
    reason = model.enable_batching(0)
    assert reason is not None and reason.startswith("a batch of 2 fails: ")
    assert "Reshape" in reason or "reshape" in reason
    assert not model.batched(0)
    items = items_for(model, 0, 2)
    out = model.run_suffix_batch(0, items)  # still served, one at a time
    np.testing.assert_array_equal(out[1]["y"], model.run_suffix(0, items[1])["y"])


def test_batch_axis_model_makes_axis_zero_symbolic_and_drops_stale_shapes() -> None:
    model = matmul_chain(2, 8)
    model.graph.value_info.append(vi("m0", [1, 8]))
    batched, rows = batch_axis_model(model)
    assert rows == 1
    for value in [*batched.graph.input, *batched.graph.output]:
        dims = value.type.tensor_type.shape.dim
        assert dims[0].dim_param == BATCH_DIM and not dims[0].HasField("dim_value")
        assert dims[1].dim_value == 8
    assert len(batched.graph.value_info) == 0
    assert model.graph.input[0].type.tensor_type.shape.dim[0].dim_value == 1, "a copy"


@pytest.mark.parametrize(
    ("inputs", "outputs", "problem"),
    [
        ([vi("x", [])], [vi("y", [])], "is a scalar"),
        ([vi("x", [1, 4])], [vi("y", [2, 4])], "disagree on axis 0 (sizes 1, 2)"),
        ([vi("x", ["n", 4])], [vi("y", [1, 4])], "axis 0 of 'x' has no static size"),
    ],
)
def test_batch_axis_model_names_what_cannot_take_a_batch(
    inputs: list[onnx.ValueInfoProto], outputs: list[onnx.ValueInfoProto], problem: str
) -> None:
    graph = helper.make_graph([node("Identity", ["x"], ["y"])], "g", inputs, outputs)
    with pytest.raises(NotBatchable, match=problem.replace("(", r"\(").replace(")", r"\)")):
        batch_axis_model(helper.make_model(graph))
