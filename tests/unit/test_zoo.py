"""The model zoo: every model exports, splits and verifies; exports are reproducible and cached;
every model takes the uint8 camera image that the robot feeds."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from skimage import data

from common import zoo
from common.errors import UserError
from common.image_input import InputAdapter
from common.models import file_digest, resolve_model
from common.partition import load_partition
from common.partition.runtime import SplitModel

# Small inputs keep export + split + verify to about a second per model on two cores.
SMALL_SHAPE = (3, 64, 64)


@pytest.mark.parametrize("name", sorted(zoo.ZOO_MODELS))
def test_every_zoo_model_splits_and_verifies(name: str) -> None:
    part = load_partition(f"zoo:{name}", input_shape=SMALL_SHAPE)
    assert part.inputs == [zoo.ZOO_INPUT_NAME] and part.outputs == [zoo.ZOO_OUTPUT_NAME]
    assert part.specs["logits"].shape == (1, zoo.NUM_CLASSES)
    # cut 0 is the camera image: uint8, channels last, one byte per value
    c, h, w = SMALL_SHAPE
    assert part.specs["input"].dtype == "uint8" and part.specs["input"].shape == (1, h, w, c)
    assert len(part.cuts) >= 8
    assert part.cuts[0].tensors == ["input"] and part.cuts[0].bytes == c * h * w
    assert all(
        c.verified and c.max_abs_err is not None and c.max_abs_err <= 1e-5 for c in part.cuts
    )
    assert not [e for e in part.excluded if not e.reason.startswith("dominated by")]
    # the last cut sends the pooled features: fewer bytes than even the uint8 image
    assert part.cuts[-1].bytes < part.cuts[0].bytes / 2
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


def test_the_front_end_is_in_the_graph(tmp_path: Path) -> None:
    model = onnx.load(str(zoo.export("resnet", tmp_path / "r.onnx", (3, 32, 48))))
    image = model.graph.input[0].type.tensor_type
    assert image.elem_type == onnx.TensorProto.UINT8
    assert [d.dim_value for d in image.shape.dim] == [1, 32, 48, 3]
    ops = [n.op_type for n in model.graph.node[:5]]
    assert ops == ["Cast", "Mul", "Sub", "Transpose", "Conv"]  # RGB: no reorder


@pytest.mark.parametrize(("channels", "order"), [(3, "rgb"), (3, "bgr"), (1, "rgb")])
def test_front_end_normalizes_a_photograph(channels: int, order: str) -> None:
    """The torch front end against (x/255 − mean)/std done by hand, on a real photograph."""
    import torch

    rgb = cv2.resize(data.astronaut(), (64, 48), interpolation=cv2.INTER_AREA)
    if channels == 1:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None]
    camera = rgb[:, :, ::-1] if order == "bgr" else rgb
    mean, std = zoo.zoo_normalization(channels)
    want = (rgb.astype(np.float32) / 255 - np.float32(mean)) / np.float32(std)
    front = zoo._camera_input(channels, order)
    got = front(torch.from_numpy(np.ascontiguousarray(camera[None]))).numpy()
    np.testing.assert_allclose(got, want.transpose(2, 0, 1)[None], rtol=1e-5, atol=1e-5)


def test_zoo_takes_what_the_robot_feeds() -> None:
    """Guards the channel order: the robot's InputAdapter turns BGR frames into what the zoo's
    CAMERA_ORDER states, as uint8 levels, for the zoo's input spec."""
    part = load_partition("zoo:vgg", input_shape=SMALL_SHAPE)
    adapter = InputAdapter(part.specs["input"])
    bgr = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    fed = adapter(bgr)
    assert fed.dtype == np.uint8 and fed.shape == (1, 64, 64, 3)
    want = bgr[:, :, ::-1] if zoo.CAMERA_ORDER == "rgb" else bgr
    np.testing.assert_array_equal(fed[0], want)


def test_full_width_models_have_the_standard_layout() -> None:
    """Parameter counts of torchvision's resnet18 and mobilenet_v2 (batch-norm included)."""
    for name, params in (("resnet18", 11_689_512), ("mobilenet_v2", 3_504_872)):
        module = zoo.get(name).build(3)
        assert sum(p.numel() for p in module.parameters()) == params, name


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
        (
            "zoo:alexnet",
            None,
            "unknown zoo model 'alexnet'; known: mobilenet, mobilenet_v2, resnet, resnet18, vgg",
        ),
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
