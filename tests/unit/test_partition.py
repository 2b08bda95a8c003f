"""The partitioner on tiny graphs built with onnx.helper: exact cut sets, sub-models, bad input.

The graph builders are `tests.helpers.onnx_graphs`.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, numpy_helper

from common.errors import UserError
from common.partition import OptionError, Partition, load_partition, parse_cuts, split_model
from common.partition import partitioner as partitioner_mod
from common.partition.graph import DataflowGraph
from common.partition.sharing import shareable_initializers
from tests.helpers.onnx_graphs import (
    IR_VERSION,
    OPSET,
    chain,
    diamond,
    dynamic,
    late_input,
    make_model,
    matmul_chain,
    node,
    residual,
    save,
    two_inputs,
    two_outputs,
    vi,
    with_if,
)


def cut_sets(part: Partition) -> list[list[str]]:
    return [c.tensors for c in part.cuts]


# ---------------------------------------------------------------------------------------------
# Exact cut sets


@pytest.mark.parametrize(
    ("build", "max_tensors", "expected"),
    [
        (chain, 2, [["x"], ["a"], ["b"]]),
        (diamond, 2, [["x"], ["a"], ["a", "b"], ["b", "c"]]),
        (diamond, 1, [["x"], ["a"]]),
        (residual, 2, [["x"], ["a"], ["a", "b"], ["a", "c"], ["d"]]),
        (residual, 1, [["x"], ["a"], ["d"]]),
        (two_inputs, 2, [["x", "z"], ["z", "a"], ["a", "b"], ["c"]]),
        # cut 0 carries both inputs even when the cap is 1: full offload is always an action
        (two_inputs, 1, [["x", "z"], ["c"]]),
        (two_outputs, 2, [["x"], ["a"], ["a", "y1"], ["y1", "c"]]),
        (two_outputs, 1, [["x"], ["a"]]),
        (late_input, 2, [["x", "z"], ["z", "a"], ["z", "b"]]),
        (late_input, 1, [["x", "z"]]),
        (with_if, 2, [["x", "flag"], ["flag", "a"], ["r"]]),
    ],
    ids=lambda v: getattr(v, "__name__", str(v)),
)
def test_auto_cuts_are_exact_and_verified(
    tmp_path: Path, build, max_tensors: int, expected: list[list[str]]
) -> None:
    src = save(build(), tmp_path / "m.onnx")
    part = split_model(src, tmp_path / "split", max_cut_tensors=max_tensors)
    assert cut_sets(part) == expected
    assert [c.index for c in part.cuts] == list(range(len(expected)))
    for cut in part.cuts:
        assert cut.verified
        assert cut.max_abs_err is not None and cut.max_abs_err <= 1e-5
        assert cut.bytes == 16 * sum(1 for t in cut.tensors if t != "flag") + (
            1 if "flag" in cut.tensors else 0
        )


def test_cut_zero_has_no_prefix_and_later_cuts_have_both_models(tmp_path: Path) -> None:
    part = split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split")
    assert part.cuts[0].prefix is None
    for cut in part.cuts[1:]:
        assert cut.prefix is not None and cut.prefix.is_file()
    for cut in part.cuts:
        assert cut.suffix is not None and cut.suffix.is_file()


def test_sub_models_pass_the_checker_and_have_the_cut_as_boundary(tmp_path: Path) -> None:
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split")
    for cut in part.cuts:
        assert cut.suffix is not None
        onnx.checker.check_model(str(cut.suffix))
        suffix = onnx.load(str(cut.suffix), load_external_data=False)
        assert [i.name for i in suffix.graph.input] == cut.tensors
        assert [o.name for o in suffix.graph.output] == ["y"]
        if cut.prefix is not None:
            onnx.checker.check_model(str(cut.prefix))
            prefix = onnx.load(str(cut.prefix), load_external_data=False)
            assert [i.name for i in prefix.graph.input] == ["x"]
            assert [o.name for o in prefix.graph.output] == cut.tensors


def test_late_input_is_an_input_of_the_suffix_not_an_output_of_the_prefix(tmp_path: Path) -> None:
    part = split_model(save(late_input(), tmp_path / "m.onnx"), tmp_path / "split")
    cut = part.cuts[2]
    assert cut.tensors == ["z", "b"]
    assert cut.prefix is not None and cut.suffix is not None
    prefix = onnx.load(str(cut.prefix), load_external_data=False)
    suffix = onnx.load(str(cut.suffix), load_external_data=False)
    assert [o.name for o in prefix.graph.output] == ["b"]
    assert [i.name for i in prefix.graph.input] == ["x"]
    assert sorted(i.name for i in suffix.graph.input) == ["b", "z"]


def test_constant_nodes_follow_the_side_that_needs_them(tmp_path: Path) -> None:
    part = split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split")
    assert all("k" not in c.tensors for c in part.cuts)
    last = part.cuts[-1]
    assert last.suffix is not None
    suffix = onnx.load(str(last.suffix), load_external_data=False)
    assert [n.op_type for n in suffix.graph.node] == ["Constant", "Add"]


def test_control_flow_node_is_reported_and_cuts_inside_it_are_excluded(tmp_path: Path) -> None:
    src = save(with_if(), tmp_path / "m.onnx")
    auto = split_model(src, tmp_path / "auto")
    assert any("If node 'branch'" in e.reason for e in auto.excluded)

    part = split_model(src, tmp_path / "user", cuts=["t_out", "a"])
    # the cut through the subgraph is excluded with a reason; the rest still works
    assert cut_sets(part) == [["x", "flag"], ["flag", "a"]]
    assert all(c.verified for c in part.cuts)
    [inside] = [e for e in part.excluded if e.tensors == ["t_out"]]
    assert "subgraph" in inside.reason and "branch" in inside.reason


# ---------------------------------------------------------------------------------------------
# Cuts given by name


def test_named_cuts_are_sorted_and_cut_zero_is_added(tmp_path: Path) -> None:
    part = split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["b", "a"])
    assert cut_sets(part) == [["x"], ["a"], ["b"]]


def test_named_multi_tensor_cut(tmp_path: Path) -> None:
    part = split_model(
        save(diamond(), tmp_path / "m.onnx"), tmp_path / "split", cuts=parse_cuts("b+c")
    )
    assert cut_sets(part) == [["x"], ["b", "c"]]
    assert part.cuts[1].verified


def test_named_cut_gains_the_inputs_its_suffix_still_needs(tmp_path: Path) -> None:
    part = split_model(save(late_input(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["b"])
    assert cut_sets(part) == [["x", "z"], ["z", "b"]]
    assert part.cuts[1].verified


def test_unknown_tensor_names_are_all_listed(tmp_path: Path) -> None:
    with pytest.raises(OptionError, match=r"unknown tensor name\(s\) in cuts: nope, zzz") as err:
        split_model(
            save(chain(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["nope", "a", "a+zzz"]
        )
    # a front end names the option its own way (the CLI: --cuts)
    assert err.value.option == "cuts"
    assert err.value.naming("--cuts") == "unknown tensor name(s) in --cuts: nope, zzz"


def test_cut_that_does_not_separate_inputs_from_outputs_is_an_error(tmp_path: Path) -> None:
    # b alone leaves c to be computed from a, which the suffix would have to recompute
    with pytest.raises(UserError, match="does not separate the inputs from the outputs"):
        split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["b"])


def test_cut_at_the_outputs_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="at the model outputs"):
        split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["y"])


def test_cut_with_a_tensor_not_needed_after_it_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="a are not used after the cut"):
        split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split", cuts=["a+b"])


def test_weights_cannot_be_cut(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"constant tensor.*W0"):
        split_model(save(matmul_chain(2, 8), tmp_path / "m.onnx"), tmp_path / "s", cuts=["W0"])


@pytest.mark.parametrize("text", ["", "a,,b", " , "])
def test_bad_cuts_option(text: str) -> None:
    with pytest.raises(OptionError, match=r"bad cuts .*expected 'auto'") as err:
        parse_cuts(text)
    assert err.value.option == "cuts"
    assert "--" not in str(err.value)  # the library does not know the CLI's flags


def test_option_error_survives_pickling() -> None:
    """Exceptions cross process pools pickled; this one is made from a template and values."""
    with pytest.raises(OptionError) as err:
        parse_cuts("a,,b")
    again = pickle.loads(pickle.dumps(err.value))
    assert isinstance(again, OptionError) and str(again) == str(err.value)
    assert again.naming("--cuts") == "bad --cuts 'a,,b': expected 'auto' or tensor names like a,b+c"


# ---------------------------------------------------------------------------------------------
# Pruning and FLOPs


def test_cut_beaten_by_a_later_one_with_the_same_flops_is_pruned(tmp_path: Path) -> None:
    src = save(matmul_chain(2, 8, out_dim=2), tmp_path / "m.onnx")
    part = split_model(src, tmp_path / "split")
    # m0 and r0 carry the same bytes after the same MatMul: only the later one stays
    assert cut_sets(part) == [["x"], ["r0"], ["m1"]]
    [dominated] = part.excluded
    assert dominated.tensors == ["m0"] and dominated.reason.startswith("dominated by r0")
    # prefix: 1x8 @ 8x8 = 2*8*8 FLOPs; suffix: 1x8 @ 8x2 = 2*8*2
    assert (part.cuts[1].prefix_flops, part.cuts[1].suffix_flops) == (128, 32)
    assert (part.cuts[0].prefix_flops, part.cuts[0].suffix_flops) == (0, 160)

    everything = split_model(src, tmp_path / "all", prune=False)
    assert cut_sets(everything) == [["x"], ["m0"], ["r0"], ["m1"]]


def test_conv_and_gemm_flops(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    w = numpy_helper.from_array(rng.standard_normal((4, 2, 3, 3)).astype(np.float32), "w")
    g = numpy_helper.from_array(rng.standard_normal((100, 5)).astype(np.float32), "g")
    model = make_model(
        [
            node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
            node("Relu", ["c"], ["r"]),
            node("Flatten", ["r"], ["f"]),
            node("Gemm", ["f", "g"], ["y"]),
        ],
        [vi("x", [1, 2, 5, 5])],
        [vi("y", [1, 5])],
        [w, g],
    )
    part = split_model(save(model, tmp_path / "m.onnx"), tmp_path / "split", prune=False)
    conv = 2 * (4 * 5 * 5) * (2 * 3 * 3)  # output elements x MACs per element
    gemm = 2 * 5 * 100
    assert part.cuts[0].suffix_flops == conv + gemm
    by_tensors = {tuple(c.tensors): c for c in part.cuts}
    assert by_tensors[("c",)].prefix_flops == conv
    assert by_tensors[("f",)].suffix_flops == gemm


# ---------------------------------------------------------------------------------------------
# Verification


def test_cut_that_fails_verification_is_excluded_with_the_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from common.partition.runtime import SplitModel

    real = SplitModel.run_suffix

    def off_by_a_bit(self, k, tensors, feeds=None):
        out = real(self, k, tensors, feeds)
        if self.partition.cuts[k].tensors == ["a", "b"]:
            out = {n: v + np.float32(1e-3) for n, v in out.items()}
        return out

    monkeypatch.setattr(SplitModel, "run_suffix", off_by_a_bit)
    part = split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split")
    assert cut_sets(part) == [["x"], ["a"], ["b", "c"]]
    assert [c.index for c in part.cuts] == [0, 1, 2]
    [bad] = part.excluded
    assert bad.tensors == ["a", "b"]
    assert "verification failed" in bad.reason and "tolerance 1e-05" in bad.reason
    names = sorted(p.name for p in (tmp_path / "split").glob("*.onnx"))
    assert not [n for n in names if n.startswith("cand")]
    assert "cut003.suffix.onnx" not in names


def test_verification_runs_the_cuts_with_the_runtime_given(tmp_path: Path) -> None:
    """The partitioner does not build the serving runtime itself: the caller's runner does."""
    from common.partition.runtime import SplitModel

    built: list[list[list[str]]] = []

    def runner(part: Partition, threads: int | None) -> SplitModel:
        built.append(cut_sets(part))
        return SplitModel(part, threads=threads, lazy=True)

    src = save(diamond(), tmp_path / "m.onnx")
    part = split_model(src, tmp_path / "split", runner=runner)
    assert built == [cut_sets(part)] and all(c.verified for c in part.cuts)
    split_model(src, tmp_path / "unverified", verify=False, runner=runner)
    assert len(built) == 1


def test_no_verify_marks_cuts_unverified(tmp_path: Path) -> None:
    part = split_model(save(diamond(), tmp_path / "m.onnx"), tmp_path / "split", verify=False)
    assert len(part.cuts) == 4
    assert all(not c.verified and c.max_abs_err is None for c in part.cuts)


# ---------------------------------------------------------------------------------------------
# Weights shared between sessions


def layer_scale_blocks(blocks: int = 2, channels: int = 256, seed: int = 0) -> onnx.ModelProto:
    """ConvNeXt's block in small: channels-last MatMul, back to NCHW, × layer scale, + skip.

    x → (Transpose to NHWC → MatMul → Transpose to NCHW → Mul(gamma) → Add skip) × blocks. The
    layer scale gamma (C,1,1), 1 KiB at 256 channels, is one initializer for every block (the
    TorchScript exporter merges equal ones; block 1 and up read it through an Identity, as in
    torchvision's convnext_tiny). onnxruntime's transpose optimizer pushes the second Transpose
    through the Mul and reshapes gamma in place to (1,1,1,C).
    """
    rng = np.random.default_rng(seed)
    gamma = rng.uniform(0.5, 1.5, (channels, 1, 1)).astype(np.float32)
    inits = [numpy_helper.from_array(gamma, "gamma")]
    nodes = []
    prev = "x"
    for b in range(blocks):
        w = (rng.standard_normal((channels, channels)) / np.sqrt(channels)).astype(np.float32)
        inits.append(numpy_helper.from_array(w, f"W{b}"))
        scale = "gamma"
        if b:
            scale = f"gamma{b}"
            nodes.append(node("Identity", ["gamma"], [scale]))
        nodes += [
            node("Transpose", [prev], [f"nhwc{b}"], perm=[0, 2, 3, 1]),
            node("MatMul", [f"nhwc{b}", f"W{b}"], [f"mm{b}"]),
            node("Transpose", [f"mm{b}"], [f"nchw{b}"], perm=[0, 3, 1, 2]),
            node("Mul", [scale, f"nchw{b}"], [f"scaled{b}"]),
            node("Add", [f"scaled{b}", prev], [f"out{b}"]),
        ]
        prev = f"out{b}"
    nodes.append(node("Identity", [prev], ["y"]))
    shape = [1, channels, 2, 2]
    return make_model(nodes, [vi("x", shape)], [vi("y", shape)], inits)


def external_initializers(split_dir: Path) -> set[str]:
    full = onnx.load(str(split_dir / "full.onnx"), load_external_data=False)
    return {t.name for t in full.graph.initializer if t.data_location == TensorProto.EXTERNAL}


def test_layer_scale_after_a_transpose_splits_with_every_cut_verified(tmp_path: Path) -> None:
    """Regression (torchvision convnext_tiny): the full model failed in verification with
    "BroadcastIterator::Append ... axis == 1 || axis == largest" because gamma was shared."""
    model = save(layer_scale_blocks(), tmp_path / "m.onnx")
    part = split_model(model, tmp_path / "split", prune=False)
    block = ["nhwc{}", "mm{}", "nchw{}", "scaled{}"]
    expected = [["x"], *(["x", t.format(0)] for t in block), ["out0"]]
    expected += [*(["out0", t.format(1)] for t in block), ["out1"]]
    assert cut_sets(part) == expected
    assert all(c.verified and c.max_abs_err == 0.0 for c in part.cuts)
    assert part.excluded == []
    # the MatMul weights are shared; the layer scale is inline in every file that uses it
    assert external_initializers(tmp_path / "split") == {"W0", "W1"}


def test_shared_are_weight_operands_and_constants_no_transpose_reaches() -> None:
    """Transposes come from Transpose nodes and layout ops (Conv), pass elementwise ops and stop
    at MatMul; a constant beside one (after_conv, scale, q_k behind its DequantizeLinear, both
    in the Concat) is not shared, nor is a graph output."""
    k = np.ones((16, 16), np.float32)  # 1 KiB each: all big enough for weights.bin
    names = ["conv_w", "after_conv", "mm_w", "bias", "scale", "aliased_w", "both", "out_k"]
    inits = [numpy_helper.from_array(k, name) for name in names]
    inits += [numpy_helper.from_array(k.astype(np.int8), name) for name in ("q_w", "q_k")]
    inits.append(numpy_helper.from_array(np.array(0.1, np.float32), "qs"))
    model = make_model(
        [
            node("Conv", ["x", "conv_w"], ["c"]),
            node("Mul", ["c", "after_conv"], ["c2"]),
            node("Flatten", ["c2"], ["f"]),
            node("MatMul", ["f", "mm_w"], ["m"]),
            node("Add", ["m", "bias"], ["b"]),
            node("Transpose", ["b"], ["t"]),
            node("Mul", ["t", "scale"], ["s"]),
            node("DequantizeLinear", ["q_k", "qs"], ["dq_k"]),
            node("Add", ["s", "dq_k"], ["s2"]),
            node("Identity", ["aliased_w"], ["alias"]),
            node("MatMul", ["s2", "alias"], ["m2"]),
            node("DequantizeLinear", ["q_w", "qs"], ["dq_w"]),
            node("MatMul", ["m2", "dq_w"], ["m3"]),
            node("MatMul", ["m3", "both"], ["m4"]),
            node("Transpose", ["m4"], ["t4"]),
            node("Concat", ["t4", "both"], ["y"], axis=0),
        ],
        [vi("x", [1, 16, 16, 1])],
        [vi("y", [32, 16]), vi("out_k", [16, 16])],
        inits,
    )
    shared = shareable_initializers(DataflowGraph(model))
    assert shared == {"conv_w", "mm_w", "bias", "aliased_w", "q_w", "qs"}


def _shared_session_fails(model: onnx.ModelProto) -> bool:
    """Whether onnxruntime still rewrites a weight shared through add_initializer in place."""
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    arrays = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    values = {name: ort.OrtValue.ortvalue_from_numpy(a) for name, a in arrays.items()}
    for name, value in values.items():
        opts.add_initializer(name, value)
    feeds = {"x": np.ones((1, 256, 2, 2), np.float32)}
    expected = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    shared = ort.InferenceSession(model.SerializeToString(), opts, ["CPUExecutionProvider"])
    try:
        return not np.array_equal(shared.run(None, feeds)[0], expected.run(None, feeds)[0])
    except Exception:
        return True


def test_shared_weight_rewritten_in_place_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Guards the safety net: a shared weight that an optimization rewrites fails the split with
    the cause named, instead of crashing in onnxruntime or verifying against wrong numbers."""
    model = layer_scale_blocks()
    if not _shared_session_fails(model):
        pytest.skip("this onnxruntime no longer rewrites a weight shared via add_initializer")
    every = {t.name for t in model.graph.initializer}
    monkeypatch.setattr(partitioner_mod, "shareable_initializers", lambda graph: every)
    with pytest.raises(UserError, match="on its own, but not with its weights shared"):
        split_model(save(model, tmp_path / "m.onnx"), tmp_path / "split")


# ---------------------------------------------------------------------------------------------
# Manifest and cache


def test_manifest_is_the_cli_contract_and_loads_back(tmp_path: Path) -> None:
    out = tmp_path / "split"
    part = split_model(save(two_outputs(), tmp_path / "m.onnx"), out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest == part.manifest()
    assert {"model", "digest", "inputs", "outputs", "cuts"} <= manifest.keys()
    assert manifest["inputs"] == ["x"] and manifest["outputs"] == ["y1", "y2"]
    for cut in manifest["cuts"]:
        assert {"index", "tensors", "bytes", "prefix", "suffix", "verified", "max_abs_err"} <= (
            cut.keys()
        )
        assert (out / cut["suffix"]).is_file()
        assert cut["prefix"] is None or (out / cut["prefix"]).is_file()
    assert Partition.load(out).manifest() == manifest


def test_split_again_into_the_same_directory_leaves_no_stale_files(tmp_path: Path) -> None:
    out = tmp_path / "split"
    split_model(save(residual(), tmp_path / "m.onnx"), out)
    split_model(save(chain(), tmp_path / "m2.onnx"), out)
    suffixes = sorted(p.name for p in out.glob("*.suffix.onnx"))
    assert suffixes == ["cut000.suffix.onnx", "cut001.suffix.onnx", "cut002.suffix.onnx"]


def test_load_partition_reads_the_cache_the_second_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    src = save(residual(), tmp_path / "m.onnx")
    first = load_partition(src)
    assert (first.dir / "manifest.json").is_file()

    def must_not_split(*args: object, **kwargs: object) -> None:
        raise AssertionError("split again instead of reading the cache")

    monkeypatch.setattr(partitioner_mod.Partitioner, "run", must_not_split)
    again = load_partition(str(src))
    assert again.dir == first.dir
    assert again.manifest() == first.manifest()
    # other options are another cache entry
    with pytest.raises(AssertionError, match="split again"):
        load_partition(src, max_cut_tensors=1)


def test_broken_cache_entry_is_split_again(tmp_path: Path) -> None:
    first = load_partition(save(residual(), tmp_path / "m.onnx"))
    suffix = first.cuts[2].suffix
    assert suffix is not None
    suffix.unlink()
    again = load_partition(tmp_path / "m.onnx")
    assert again.dir == first.dir
    assert suffix.is_file()


def test_cache_entry_follows_the_model_digest(tmp_path: Path) -> None:
    src = tmp_path / "m.onnx"
    first = load_partition(save(diamond(), src))
    second = load_partition(save(residual(), src))
    assert first.digest != second.digest
    assert first.dir != second.dir
    assert cut_sets(second)[-1] == ["d"]


# ---------------------------------------------------------------------------------------------
# Input shapes


def test_dynamic_batch_becomes_one(tmp_path: Path) -> None:
    part = split_model(save(dynamic(["N", 4]), tmp_path / "m.onnx"), tmp_path / "split")
    assert part.specs["x"].shape == (1, 4)
    assert part.specs["a"].shape == (1, 4)


def test_other_dynamic_dimensions_need_an_input_shape(tmp_path: Path) -> None:
    src = save(dynamic([1, "L"]), tmp_path / "m.onnx")
    with pytest.raises(OptionError, match=r"dynamic dimension L at axis 1.*input_shape") as err:
        split_model(src, tmp_path / "split")
    assert err.value.option == "input_shape"
    part = split_model(src, tmp_path / "split", input_shape=(6,))  # batch left out
    assert part.specs["a"].shape == (1, 6)
    assert part.cuts[1].bytes == 24
    part = split_model(src, tmp_path / "split", input_shape={"x": (1, 3)})
    assert part.specs["y"].shape == (1, 3)


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        ((2, 6), "axis 0 is fixed at 1"),
        ((1, 2, 3), "has 3 dimensions but input 'x' has 2"),
        ({"q": (1, 2)}, "unknown input.*q"),
    ],
)
def test_bad_input_shapes(tmp_path: Path, shape: object, message: str) -> None:
    src = save(dynamic([1, "L"]), tmp_path / "m.onnx")
    with pytest.raises(UserError, match=message):
        split_model(src, tmp_path / "split", input_shape=shape)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# Bad files


def test_not_an_onnx_file(tmp_path: Path) -> None:
    src = tmp_path / "notes.onnx"
    src.write_text("this is not a model\n")
    with pytest.raises(UserError, match="is not an ONNX model"):
        split_model(src, tmp_path / "split")


def test_truncated_file(tmp_path: Path) -> None:
    data = matmul_chain(2, 16).SerializeToString()
    src = tmp_path / "cut.onnx"
    src.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match="ONNX model") as err:
        split_model(src, tmp_path / "split")
    assert "\n" not in str(err.value)


def test_empty_file(tmp_path: Path) -> None:
    src = tmp_path / "empty.onnx"
    src.write_bytes(b"")
    with pytest.raises(UserError, match="is not an ONNX model"):
        split_model(src, tmp_path / "split")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="model file not found"):
        split_model(tmp_path / "nope.onnx", tmp_path / "split")


def relu_model(*, opset: int = OPSET, ir_version: int = IR_VERSION) -> onnx.ModelProto:
    return make_model(
        [node("Relu", ["x"], ["y"])],
        [vi("x", [1, 4])],
        [vi("y", [1, 4])],
        opset=opset,
        ir_version=ir_version,
    )


def first_refused_by_onnxruntime(field: str, start: int) -> int:
    """The lowest IR version or opset (from `start` up) the installed onnxruntime refuses.

    onnxruntime publishes no such limit, so ask it: load tiny models until one is refused.
    Regression guard: a hard-coded "too new" number stops being too new with the next release.
    """
    for value in range(start, start + 64):
        model = relu_model(**{field: value})
        try:
            ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        except Exception:
            return value
    raise AssertionError(f"onnxruntime accepted every {field} from {start} to {start + 63}")


def test_ir_version_newer_than_onnxruntime(tmp_path: Path) -> None:
    too_new = first_refused_by_onnxruntime("ir_version", IR_VERSION)
    model = relu_model()
    model.ir_version = too_new
    # Whichever refuses first names the version: onnxruntime when it lags onnx, else onnx's checker.
    refused_by = (
        "onnxruntime cannot run.*IR version:" if too_new <= onnx.IR_VERSION else "ir_version"
    )
    with pytest.raises(UserError, match=rf"{refused_by} {too_new}") as err:
        split_model(save(model, tmp_path / "m.onnx"), tmp_path / "split")
    assert "onnxruntime_src" not in str(err.value)


def test_opset_newer_than_onnxruntime(tmp_path: Path) -> None:
    too_new = first_refused_by_onnxruntime("opset", OPSET)
    model = relu_model(opset=too_new)
    with pytest.raises(UserError, match=rf"onnxruntime cannot run.*[Oo]pset {too_new}") as err:
        split_model(save(model, tmp_path / "m.onnx"), tmp_path / "split")
    assert "onnxruntime_src" not in str(err.value)


def test_out_dir_that_is_a_file(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match="not a directory"):
        split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "file")
