"""The model zoo: every model exports, splits and verifies; exports are reproducible and cached."""

from __future__ import annotations

from pathlib import Path

import onnx
import pytest

from common import zoo
from common.errors import UserError
from common.models import file_digest, resolve_model
from common.partition import load_partition
from common.split_runtime import SplitModel

# Small inputs keep export + split + verify to about a second per model on two cores.
SMALL_SHAPE = (3, 64, 64)


@pytest.mark.parametrize("name", sorted(zoo.ZOO_MODELS))
def test_every_zoo_model_splits_and_verifies(name: str) -> None:
    part = load_partition(f"zoo:{name}", input_shape=SMALL_SHAPE)
    assert part.inputs == [zoo.ZOO_INPUT_NAME] and part.outputs == [zoo.ZOO_OUTPUT_NAME]
    assert part.specs["logits"].shape == (1, zoo.NUM_CLASSES)
    assert len(part.cuts) >= 8
    assert part.cuts[0].tensors == ["input"]
    assert all(
        c.verified and c.max_abs_err is not None and c.max_abs_err <= 1e-5 for c in part.cuts
    )
    assert not [e for e in part.excluded if not e.reason.startswith("dominated by")]
    # the last cut sends the pooled features: far fewer bytes than the image
    assert part.cuts[-1].bytes < part.cuts[0].bytes / 20
    flops = [c.prefix_flops for c in part.cuts]
    assert flops == sorted(flops) and flops[0] == 0


def test_graph_shapes_differ_as_described(tmp_path: Path) -> None:
    def two_tensor_cuts(name: str) -> int:
        part = load_partition(f"zoo:{name}", input_shape=SMALL_SHAPE)
        return sum(len(c.tensors) == 2 for c in part.cuts)

    assert two_tensor_cuts("vgg") == 0  # a chain
    assert two_tensor_cuts("resnet") > 0  # skips cross the cuts inside a block
    ref = resolve_model("zoo:mobilenet", SMALL_SHAPE)
    model = onnx.load(str(ref.path))
    groups = [a.i for n in model.graph.node if n.op_type == "Conv" for a in n.attribute]
    assert any(g > 1 for g in groups if g)  # depthwise convolutions


def test_export_is_reproducible(tmp_path: Path) -> None:
    a = zoo.export("vgg", tmp_path / "a.onnx", (3, 32, 32))
    b = zoo.export("vgg", tmp_path / "b.onnx", (3, 32, 32))
    assert file_digest(a) == file_digest(b)
    c = zoo.export("vgg", tmp_path / "c.onnx", (3, 32, 48))
    assert file_digest(c) != file_digest(a)


def test_zoo_model_is_exported_once_then_read_from_the_cache(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    first = resolve_model("zoo:resnet", (1, *SMALL_SHAPE))  # a batch of 1 may be given
    assert first.name == "resnet" and first.path.is_file()

    def must_not_export(*args: object) -> Path:
        raise AssertionError("exported again instead of reading the cache")

    monkeypatch.setattr(zoo, "export", must_not_export)
    again = resolve_model("zoo:resnet", SMALL_SHAPE)
    assert (again.path, again.digest) == (first.path, first.digest)


def test_split_model_runs_from_a_zoo_spec() -> None:
    rt = SplitModel(load_partition("zoo:vgg", input_shape=SMALL_SHAPE), threads=1)
    assert rt.input_names == ["input"]
    assert rt.weight_bytes > 100_000


@pytest.mark.parametrize(
    ("spec", "shape", "message"),
    [
        ("zoo:alexnet", None, "unknown zoo model 'alexnet'; known: mobilenet, resnet, vgg"),
        ("zoo:vgg", (3, 16, 64), "height must be 32..4096"),
        ("zoo:vgg", (240, 320), "CxHxW"),
        ("", None, "empty model name"),
    ],
)
def test_bad_zoo_specs(spec: str, shape: tuple[int, ...] | None, message: str) -> None:
    with pytest.raises(UserError, match=message):
        resolve_model(spec, shape)


@pytest.mark.parametrize("text", ["3x240", "3x240x320", "1X3X8X8"])
def test_parse_shape(text: str) -> None:
    assert zoo.parse_shape(text) == tuple(int(p) for p in text.lower().split("x"))


@pytest.mark.parametrize("text", ["", "3xx4", "3x-1", "axb", "3x0x4"])
def test_parse_shape_rejects(text: str) -> None:
    with pytest.raises(UserError, match="bad shape"):
        zoo.parse_shape(text)
