"""`model prep` on tiny onnx.helper image models: the front end's graph, its numbers, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, numpy_helper

from common import prep
from common.errors import UserError
from common.prep import ChannelOrder, Layout, prep_model
from tests.helpers.onnx_graphs import make_model, node, save, vi

IMAGENET = {"mean": (0.485, 0.456, 0.406), "std": (0.229, 0.224, 0.225)}


def conv_net(
    shape: list[int | str], *, nhwc: bool = False, elem: int = TensorProto.FLOAT, name: str = "x"
) -> onnx.ModelProto:
    """name → [Transpose to NCHW] → Conv 3→4 → Relu → global average pool → Flatten → y."""
    np_dtype = np.float16 if elem == TensorProto.FLOAT16 else np.float32
    rng = np.random.default_rng(0)
    w = numpy_helper.from_array(rng.standard_normal((4, 3, 3, 3)).astype(np_dtype), "w")
    nodes = []
    x = name
    if nhwc:
        nodes.append(node("Transpose", [x], ["nchw"], perm=[0, 3, 1, 2]))
        x = "nchw"
    nodes += [
        node("Conv", [x, "w"], ["c"], pads=[1, 1, 1, 1]),
        node("Relu", ["c"], ["r"]),
        node("GlobalAveragePool", ["r"], ["p"]),
        node("Flatten", ["p"], ["y"]),
    ]
    return make_model(nodes, [vi(name, shape, elem)], [vi("y", [shape[0], 4], elem)], [w])


def run(path: Path, feeds: dict[str, np.ndarray]) -> np.ndarray:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return np.asarray(session.run(["y"], feeds)[0])


def by_hand(rgb: np.ndarray, mean: tuple[float, ...], std: tuple[float, ...]) -> np.ndarray:
    x = (rgb.astype(np.float32) / 255 - np.array(mean, np.float32)) / np.array(std, np.float32)
    return x.transpose(2, 0, 1)[None]


def test_bgr_nchw_front_end_graph_and_numbers(tmp_path: Path) -> None:
    src = save(conv_net(["N", 3, "H", "W"]), tmp_path / "m.onnx")
    out = tmp_path / "m.prep.onnx"
    result = prep_model(src, out, camera_order=ChannelOrder.BGR, input_size=(48, 64), **IMAGENET)
    assert result.input_name == "x" and result.input_dtype == "uint8"
    assert result.input_shape == ["N", 48, 64, 3]
    assert result.outputs == ["y"] and result.verify_size == (48, 64)
    assert result.max_abs_err <= result.tolerance
    model = onnx.load(str(out))
    onnx.checker.check_model(model)
    ops = [n.op_type for n in model.graph.node]
    assert ops[:5] == ["Cast", "Gather", "Mul", "Sub", "Transpose"] and ops[5] == "Conv"
    assert model.graph.input[0].type.tensor_type.elem_type == TensorProto.UINT8
    # An image other than the one prep verified on: BGR camera levels in, RGB normalized by hand.
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    want = run(src, {"x": by_hand(rgb, **IMAGENET)})
    got = run(out, {"x": np.ascontiguousarray(rgb[None, :, :, ::-1])})
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_rgb_nhwc_needs_no_reorder_nor_transpose(tmp_path: Path) -> None:
    src = save(conv_net([1, 32, 40, 3], nhwc=True), tmp_path / "m.onnx")
    result = prep_model(src, tmp_path / "p.onnx", layout=Layout.NHWC, mean=(0.5,) * 3)
    assert result.input_shape == [1, 32, 40, 3] and result.verify_size == (32, 40)
    ops = [n.op_type for n in onnx.load(str(tmp_path / "p.onnx")).graph.node]
    assert ops[:4] == ["Cast", "Mul", "Sub", "Transpose"]  # the model's own Transpose follows
    rgb = np.random.default_rng(2).integers(0, 256, (1, 32, 40, 3), dtype=np.uint8)
    want = run(src, {"x": rgb.astype(np.float32) / 255 - np.float32(0.5)})
    np.testing.assert_allclose(run(tmp_path / "p.onnx", {"x": rgb}), want, rtol=1e-5, atol=1e-5)


def test_dynamic_size_stays_dynamic_and_is_verified_at_the_default(tmp_path: Path) -> None:
    result = prep_model(save(conv_net([1, 3, "H", "W"]), tmp_path / "m.onnx"), tmp_path / "p.onnx")
    assert result.input_shape == [1, "H", "W", 3]
    assert result.verify_size == (prep.VERIFY_SIDE_PX, prep.VERIFY_SIDE_PX)


def test_float16_model(tmp_path: Path) -> None:
    src = save(conv_net([1, 3, 32, 32], elem=TensorProto.FLOAT16), tmp_path / "m.onnx")
    result = prep_model(src, tmp_path / "p.onnx", **IMAGENET)
    assert result.max_abs_err <= result.tolerance


def test_front_end_names_do_not_collide_with_the_model(tmp_path: Path) -> None:
    src = save(conv_net([1, 3, 32, 32], name="prep/x"), tmp_path / "m.onnx")
    result = prep_model(src, tmp_path / "p.onnx")
    assert result.input_name == "prep/x"
    names = [n.name for n in onnx.load(str(tmp_path / "p.onnx")).graph.node]
    assert names[0].startswith("prep1/")


def test_a_wrong_front_end_is_caught_and_not_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Regression guard: the photograph check must fail when the graph forgets BGR→RGB."""
    forget_reorder = prep._Prep._front_end

    def front_end(self: prep._Prep, model: onnx.ModelProto, image: object) -> onnx.ModelProto:
        order, self.camera_order = self.camera_order, ChannelOrder.RGB
        try:
            return forget_reorder(self, model, image)  # type: ignore[arg-type]
        finally:
            self.camera_order = order

    monkeypatch.setattr(prep._Prep, "_front_end", front_end)
    src = save(conv_net([1, 3, 32, 32]), tmp_path / "m.onnx")
    out = tmp_path / "p.onnx"
    with pytest.raises(UserError, match=r"differs from the original .* nothing written"):
        prep_model(src, out, camera_order=ChannelOrder.BGR, **IMAGENET)
    assert list(tmp_path.iterdir()) == [src]


def two_inputs() -> onnx.ModelProto:
    return make_model(
        [node("Add", ["a", "b"], ["y"])],
        [vi("a", [1, 3, 8, 8]), vi("b", [1, 3, 8, 8])],
        [vi("y", [1, 3, 8, 8])],
    )


@pytest.mark.parametrize(
    ("model", "kwargs", "message"),
    [
        (two_inputs(), {}, r"has 2 inputs \(a, b\); prep wraps a model with one image input"),
        (conv_net([1, 3, 8, 8], elem=TensorProto.INT64), {}, "is int64, not float"),
        (conv_net([1, 3, 8, 8], elem=TensorProto.UINT8), {}, "already takes integer levels"),
        (
            make_model([node("Relu", ["x"], ["y"])], [vi("x", [1, 3, 8])], [vi("y", [1, 3, 8])]),
            {},
            r"has shape \[1, 3, 8\]: not an image model",
        ),
        (conv_net([1, 1, 8, 8]), {}, "has 1 channel"),
        (conv_net([1, 8, 8, 3]), {}, r"is the layout nhwc\? \(--layout nhwc\)"),
        (conv_net([1, 3, "H", "W"]), {"layout": Layout.NHWC}, r"--layout nchw"),
        (conv_net([1, 3, 8, 8]), {"mean": (0.5, 0.5)}, "--mean needs 3 values"),
        (conv_net([1, 3, 8, 8]), {"std": (1.0, 0.0, 1.0)}, "--std values must be positive"),
        (conv_net([1, 3, 8, 8]), {"std": (1.0, float("nan"), 1.0)}, "must be finite"),
        (
            conv_net([1, 3, 8, "W"]),
            {"input_size": (16, 16)},
            "does not match input 'x': its height is fixed at 8",
        ),
    ],
)
def test_bad_input_names_the_problem(
    tmp_path: Path, model: onnx.ModelProto, kwargs: dict[str, object], message: str
) -> None:
    src = save(model, tmp_path / "m.onnx")
    with pytest.raises(UserError, match=message):
        prep_model(src, tmp_path / "p.onnx", **kwargs)  # type: ignore[arg-type]
    assert not (tmp_path / "p.onnx").exists()


def test_old_opset_is_refused(tmp_path: Path) -> None:
    src = save(conv_net([1, 3, 8, 8]), tmp_path / "m.onnx")
    model = onnx.load(str(src))
    model.opset_import[0].version = 6
    save(model, src)
    with pytest.raises(UserError, match="opset"):
        prep_model(src, tmp_path / "p.onnx")


@pytest.mark.parametrize(
    ("text", "values"), [("0.485,0.456,0.406", (0.485, 0.456, 0.406)), ("1, 2", (1.0, 2.0))]
)
def test_parse_channel_values(text: str, values: tuple[float, ...]) -> None:
    assert prep.parse_channel_values(text, "--mean") == values


@pytest.mark.parametrize("text", ["a,b,c", "1,,2", ""])
def test_parse_channel_values_rejects(text: str) -> None:
    with pytest.raises(UserError, match="--mean"):
        prep.parse_channel_values(text, "--mean")


def test_parse_size_and_layout() -> None:
    assert prep.parse_size("240x320") == (240, 320)
    assert prep.parse_layout("NHWC") is Layout.NHWC
    with pytest.raises(UserError, match="HxW"):
        prep.parse_size("3x240x320")
    with pytest.raises(UserError, match="--layout must be nchw or nhwc"):
        prep.parse_layout("chw")
