"""The model zoo: every model builds, splits and verifies; builds are reproducible (bytes pinned)
and cached; every model takes the uint8 camera image that the robot feeds; no torch anywhere."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import pytest
from skimage import data

from common import zoo
from common.errors import UserError
from common.image_input import InputAdapter
from common.models import file_digest, resolve_model
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.zoo_nets import build_network, front_end_model

ROOT = Path(__file__).resolve().parents[2]

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
    """The graph's front end against (x/255 − mean)/std done by hand, on a real photograph."""
    rgb = cv2.resize(data.astronaut(), (64, 48), interpolation=cv2.INTER_AREA)
    if channels == 1:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None]
    camera = rgb[:, :, ::-1] if order == "bgr" else rgb
    mean, std = zoo.zoo_normalization(channels)
    want = (rgb.astype(np.float32) / 255 - np.asarray(mean, np.float32)) / np.asarray(
        std, np.float32
    )
    front = front_end_model(channels, 48, 64, order)
    session = ort.InferenceSession(front.SerializeToString(), providers=["CPUExecutionProvider"])
    (got,) = session.run(None, {"input": np.ascontiguousarray(camera[None])})
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
    """Parameter counts of torchvision's resnet18 and mobilenet_v2 (batch-norm included), and the
    graphs as the torch exporter wrote them: batch norms folded into the convolutions, ReLU6 as
    Clip, the head GlobalAveragePool, Flatten, Gemm."""
    for name, params, convs in (("resnet18", 11_689_512, 20), ("mobilenet_v2", 3_504_872, 52)):
        model, layers = build_network(name, (3, 224, 224))
        assert sum(layer.parameter_count for layer in layers) == params, name
        ops = [n.op_type for n in model.graph.node]
        assert ops.count("Conv") == convs and "BatchNormalization" not in ops, name
        assert ops[-3:] == ["GlobalAveragePool", "Flatten", "Gemm"], name
        assert ("Clip" in ops) == (name == "mobilenet_v2"), name


# sha256 of the built files. A change here means every robot and cloud builds a different file
# for the same name: bump zoo.ZOO_FORMAT (the cache key) with it. Pinned, so that a change of
# platform, NumPy or onnx that changed the bytes (and the digest the fleet matches models by)
# shows here first.
PINNED_DIGESTS = {
    ("vgg", (3, 32, 32)): "4afe7f81a4a498a0c4286d14e375e017b82c6c01cb7e96c395ab5ac28b2842e6",
    ("mobilenet", (1, 32, 48)): "1677252c7ece76f95ea051cf2f2400cb5cc0eef71927bd314000f7a3994ec46a",
}


@pytest.mark.parametrize(("name", "shape"), sorted(PINNED_DIGESTS))
def test_build_is_reproducible(tmp_path: Path, name: str, shape: tuple[int, int, int]) -> None:
    a = zoo.export(name, tmp_path / "a.onnx", shape)
    b = zoo.export(name, tmp_path / "b.onnx", shape)
    assert file_digest(a) == file_digest(b) == PINNED_DIGESTS[name, shape]
    c = zoo.export(name, tmp_path / "c.onnx", (shape[0], 64, 64))
    assert file_digest(c) != file_digest(a)


def test_building_every_model_imports_no_torch() -> None:
    """The zoo, the partitioner and the profiler run without torch (the runtime has none)."""
    code = (
        "import json, sys\n"
        "from common import zoo\n"
        "from common.profiler import profile_model\n"
        "for name in zoo.ZOO_MODELS:\n"
        "    zoo.get(name).build((3, 32, 32))\n"
        "profile_model('zoo:resnet', runs=1, input_shape=(3, 32, 32))\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] == 'torch')))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []


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
