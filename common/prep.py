"""``elasticfog model prep``: wrap a float-image ONNX model so that it takes the camera image.

The wrapped model's input is the camera image as the robot holds it: uint8 N×H×W×3, channels last,
raw levels 0..255, in RGB or BGR order. A front end in the graph does what a preprocessing script
would: cast to float, reorder BGR to RGB (a Gather; the model is taken to expect RGB), scale by
1/255, subtract the mean and divide by the standard deviation per channel, and transpose to N×C×H×W
when the original model is channels first. The input keeps the original input's name and the
outputs keep theirs, so configs and manifests read the same; cut 0 of the partitioner becomes the
uint8 image (a quarter of the float tensor's bytes).

Stages, one private step each: load and check the model, find its one image input, build the front
end, merge it before the model (``onnx.compose.merge_models``), check the result, and verify it on
a real photograph (scikit-image's astronaut, resized with OpenCV) against the original model fed
with the same normalization done by hand in numpy. The file is written next to ``--out`` and
renamed into place only when everything passed.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from common.errors import UserError

CHANNELS = 3
PIXEL_MAX = 255.0
# Verification: the largest absolute difference over an output must stay within this fraction of
# the output's scale (its largest absolute value in the reference run).
PREP_RTOL = 1e-4
# A dynamic height or width is verified at this size (the file keeps it dynamic).
VERIFY_SIDE_PX = 224
# Cast's `to` is an int from opset 6; onnxruntime runs opset 7 and later.
MIN_OPSET = 7
FRONT_END_PREFIX = "prep/"
PRODUCER_NAME = "elasticfog model prep"
_FLOAT_TYPES = {TensorProto.FLOAT, TensorProto.FLOAT16, TensorProto.DOUBLE}


class Layout(str, Enum):
    """Layout of the original model's image input."""

    NCHW = "nchw"
    NHWC = "nhwc"


class ChannelOrder(str, Enum):
    """Channel order of the camera image (the model is taken to expect RGB)."""

    RGB = "rgb"
    BGR = "bgr"


@dataclass(frozen=True)
class PrepResult:
    """What was written: the new input, the front end's settings and the verification."""

    path: Path
    input_name: str
    input_shape: list[int | str]
    input_dtype: str
    camera_order: ChannelOrder
    layout: Layout
    mean: tuple[float, ...]
    std: tuple[float, ...]
    outputs: list[str]
    verify_size: tuple[int, int]
    max_abs_err: float
    tolerance: float

    def to_json(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "input": {
                "name": self.input_name,
                "shape": self.input_shape,
                "dtype": self.input_dtype,
            },
            "camera_order": self.camera_order.value,
            "model_order": ChannelOrder.RGB.value,
            "layout": self.layout.value,
            "mean": list(self.mean),
            "std": list(self.std),
            "outputs": self.outputs,
            "verify_size": list(self.verify_size),
            "max_abs_err": self.max_abs_err,
            "tolerance": self.tolerance,
        }


def prep_model(
    model: str | Path,
    out: Path,
    *,
    mean: tuple[float, ...] = (0.0, 0.0, 0.0),
    std: tuple[float, ...] = (1.0, 1.0, 1.0),
    layout: Layout = Layout.NCHW,
    camera_order: ChannelOrder = ChannelOrder.RGB,
    input_size: tuple[int, int] | None = None,
) -> PrepResult:
    """Wrap ``model`` (an ONNX file with one float image input) to take the uint8 camera image.

    ``mean`` and ``std`` are per channel in the model's (RGB) order, in units of the [0, 1]
    image; ``layout`` is the original model's input layout; ``camera_order`` the order of the
    camera image; ``input_size`` (H, W) fixes a dynamic height and width. Raises UserError naming
    the problem; nothing is written unless the wrapped model passes the checker and matches the
    original within PREP_RTOL of the output scale on a real photograph.
    """
    return _Prep(
        model, _channel_values(mean, "--mean"), _channel_values(std, "--std", positive=True),
        Layout(layout), ChannelOrder(camera_order), input_size,
    ).run(Path(out))  # fmt: skip


def parse_channel_values(text: str, option: str) -> tuple[float, ...]:
    """``0.485,0.456,0.406`` → floats (prep_model checks that there are three); raises
    UserError naming ``option`` on anything that is not a number."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise UserError(f"{option} {text!r}: expected {CHANNELS} numbers joined by ','") from None
    return values


def parse_layout(text: str) -> Layout:
    """``nchw`` or ``nhwc`` (any case) → Layout; raises UserError on anything else."""
    try:
        return Layout(text.strip().lower())
    except ValueError:
        known = " or ".join(v.value for v in Layout)
        raise UserError(f"--layout must be {known}, got {text!r}") from None


def parse_size(text: str) -> tuple[int, int]:
    """``240x320`` → (240, 320); raises UserError on anything else."""
    from common.zoo import parse_shape

    dims = parse_shape(text)
    if len(dims) != 2:
        raise UserError(f"--input-shape {text!r}: prep takes the image size as HxW, e.g. 224x224")
    return dims[0], dims[1]


def _channel_values(
    values: tuple[float, ...], option: str, *, positive: bool = False
) -> tuple[float, ...]:
    values = tuple(float(v) for v in values)
    if len(values) != CHANNELS:
        raise UserError(
            f"{option} needs {CHANNELS} values, one per channel in RGB order, got {len(values)}: "
            + ",".join(f"{v:g}" for v in values)
        )
    if not all(math.isfinite(v) for v in values):
        raise UserError(f"{option} values must be finite numbers")
    if positive and not all(v > 0 for v in values):
        raise UserError(f"{option} values must be positive (they divide), got {values}")
    return values


@dataclass(frozen=True)
class _ImageInput:
    """The original model's image input: name, element type and its dimensions by role."""

    name: str
    elem_type: int
    batch: onnx.TensorShapeProto.Dimension
    height: onnx.TensorShapeProto.Dimension
    width: onnx.TensorShapeProto.Dimension


class _Prep:
    """One wrapping: the stages from loading the model to the verified file, one step each."""

    def __init__(
        self,
        model: str | Path,
        mean: tuple[float, ...],
        std: tuple[float, ...],
        layout: Layout,
        camera_order: ChannelOrder,
        input_size: tuple[int, int] | None,
    ) -> None:
        self.spec = str(model)
        self.mean = mean
        self.std = std
        self.layout = layout
        self.camera_order = camera_order
        self.input_size = input_size

    def run(self, out: Path) -> PrepResult:
        from common.models import resolve_model
        from common.partition import load_onnx

        if out.is_dir():
            raise UserError(f"--out {out} is a directory; give a file name such as model.prep.onnx")
        ref = resolve_model(self.spec)
        original = load_onnx(ref.path)  # onnx.checker before
        image = self._image_input(original)
        front = self._front_end(original, image)
        wrapped = self._merge(front, original, image)
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
        os.close(fd)
        tmp = Path(tmp_name)
        try:
            onnx.save_model(wrapped, str(tmp))
            try:
                onnx.checker.check_model(str(tmp))  # and after
            except Exception as exc:
                raise UserError(f"the wrapped model fails the ONNX checker: {exc}") from None
            size = self._verify_size(image)
            err, tolerance = self._verify(ref.path, tmp, image, size)
            os.replace(tmp, out)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        new_input = wrapped.graph.input[0]
        return PrepResult(
            path=out,
            input_name=new_input.name,
            input_shape=_dims(new_input),
            input_dtype="uint8",
            camera_order=self.camera_order,
            layout=self.layout,
            mean=self.mean,
            std=self.std,
            outputs=[o.name for o in wrapped.graph.output],
            verify_size=size,
            max_abs_err=err,
            tolerance=tolerance,
        )

    # -- stages --

    def _image_input(self, model: onnx.ModelProto) -> _ImageInput:
        """The one float image input; UserError naming what makes the model something else."""
        inits = {t.name for t in model.graph.initializer}
        inputs = [vi for vi in model.graph.input if vi.name not in inits]
        if len(inputs) != 1:
            names = ", ".join(vi.name for vi in inputs) or "none"
            raise UserError(
                f"{self.spec} has {len(inputs)} inputs ({names}); prep wraps a model with one "
                "image input"
            )
        vi = inputs[0]
        if not vi.type.HasField("tensor_type"):
            raise UserError(f"input {vi.name!r} is not a tensor: not an image model")
        tt = vi.type.tensor_type
        elem = tt.elem_type
        if elem not in _FLOAT_TYPES:
            kind = TensorProto.DataType.Name(elem).lower()
            already = " (it already takes integer levels)" if elem == TensorProto.UINT8 else ""
            raise UserError(
                f"input {vi.name!r} is {kind}, not float{already}: prep wraps a float-image model"
            )
        dims = list(tt.shape.dim) if tt.HasField("shape") else []
        expected = "N×C×H×W" if self.layout is Layout.NCHW else "N×H×W×C (--layout nhwc)"
        if len(dims) != 4:
            shown = [_dim_value(d) for d in dims] if tt.HasField("shape") else "unknown"
            raise UserError(
                f"input {vi.name!r} has shape {shown}: not an image model (expected {expected})"
            )
        if self.layout is Layout.NCHW:
            batch, channels, height, width = dims
        else:
            batch, height, width, channels = dims
        other = dims[3] if self.layout is Layout.NCHW else dims[1]
        if _fixed(channels) != CHANNELS and (_fixed(other) == CHANNELS or _fixed(channels)):
            # Fixed at another count, or dynamic where the other layout's channel axis holds 3.
            flag = "nhwc" if self.layout is Layout.NCHW else "nchw"
            hint = f"; is the layout {flag}? (--layout {flag})" if _fixed(other) == CHANNELS else ""
            count = _fixed(channels) or "a dynamic number of"
            raise UserError(
                f"input {vi.name!r} of shape {[_dim_value(d) for d in dims]} has {count} "
                f"channel(s) as {expected}; prep makes {CHANNELS}-channel camera inputs{hint}"
            )
        height, width = self._fix_size(vi.name, height, width)
        return _ImageInput(vi.name, elem, batch, height, width)

    def _fix_size(
        self,
        name: str,
        height: onnx.TensorShapeProto.Dimension,
        width: onnx.TensorShapeProto.Dimension,
    ) -> tuple[onnx.TensorShapeProto.Dimension, onnx.TensorShapeProto.Dimension]:
        """Height and width of the new input: --input-shape fixes dynamic ones, must match fixed."""
        if self.input_size is None:
            return height, width
        fixed = []
        for label, dim, want in zip(
            ("height", "width"), (height, width), self.input_size, strict=True
        ):
            if dim.HasField("dim_value") and dim.dim_value != want:
                raise UserError(
                    f"--input-shape {self.input_size[0]}x{self.input_size[1]} does not match "
                    f"input {name!r}: its {label} is fixed at {dim.dim_value}"
                )
            fixed.append(onnx.TensorShapeProto.Dimension(dim_value=want))
        return fixed[0], fixed[1]

    def _front_end(self, model: onnx.ModelProto, image: _ImageInput) -> onnx.ModelProto:
        """uint8 N×H×W×3 → Cast → (Gather BGR→RGB) → Mul → Sub → (Cast) → (Transpose) → input.

        The reorder comes after the cast so that no cut but cut 0 sends uint8 levels: a cut
        after a uint8 Gather would send as many bytes as cut 0 for nothing. (x/255 − mean)/std is
        computed in float32 as x·(1/(255·std)) − mean/std (one Mul and one Sub per pixel), then
        cast to the model's type (float16, double) if it is another. Names carry a prefix no
        name of the model uses, so the merge cannot collide.
        """
        p = _free_prefix(model)
        scale = np.array([1.0 / (PIXEL_MAX * s) for s in self.std], dtype=np.float32)
        offset = np.array([m / s for m, s in zip(self.mean, self.std, strict=True)], np.float32)
        inits = [
            numpy_helper.from_array(scale, f"{p}scale"),
            numpy_helper.from_array(offset, f"{p}offset"),
        ]
        nodes = [
            helper.make_node("Cast", [image.name], [f"{p}float"], f"{p}cast", to=TensorProto.FLOAT)
        ]
        x = f"{p}float"
        if self.camera_order is ChannelOrder.BGR:
            inits.append(numpy_helper.from_array(np.array([2, 1, 0], np.int64), f"{p}bgr"))
            nodes.append(helper.make_node("Gather", [x, f"{p}bgr"], [f"{p}rgb"], f"{p}rgb", axis=3))
            x = f"{p}rgb"
        nodes += [
            helper.make_node("Mul", [x, f"{p}scale"], [f"{p}scaled"], f"{p}scale"),
            helper.make_node("Sub", [f"{p}scaled", f"{p}offset"], [f"{p}normalized"], f"{p}norm"),
        ]
        x = f"{p}normalized"
        if image.elem_type != TensorProto.FLOAT:
            # float32 arithmetic, then the model's type: as a script would do it in numpy.
            nodes.append(
                helper.make_node("Cast", [x], [f"{p}typed"], f"{p}typed", to=image.elem_type)
            )
            x = f"{p}typed"
        if self.layout is Layout.NCHW:
            nodes.append(
                helper.make_node("Transpose", [x], [f"{p}nchw"], f"{p}nchw", perm=[0, 3, 1, 2])
            )
            x = f"{p}nchw"
        channels = onnx.TensorShapeProto.Dimension(dim_value=CHANNELS)
        hw = [image.height, image.width]
        in_dims = [image.batch, *hw, channels]
        out_dims = [image.batch, channels, *hw] if self.layout is Layout.NCHW else in_dims
        graph = helper.make_graph(
            nodes,
            "camera_front_end",
            [_value_info(image.name, TensorProto.UINT8, in_dims)],
            [_value_info(x, image.elem_type, out_dims)],
            inits,
        )
        opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 0)
        if opset < MIN_OPSET:
            raise UserError(
                f"{self.spec} uses opset {opset or 'none'} of the default domain; prep needs "
                f"{MIN_OPSET} or later"
            )
        return helper.make_model(
            graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=model.ir_version
        )

    def _merge(
        self, front: onnx.ModelProto, model: onnx.ModelProto, image: _ImageInput
    ) -> onnx.ModelProto:
        front_out = front.graph.output[0].name
        try:
            merged = onnx.compose.merge_models(
                front, model, io_map=[(front_out, image.name)], producer_name=PRODUCER_NAME
            )
        except (ValueError, onnx.checker.ValidationError) as exc:
            raise UserError(f"cannot put the front end before {self.spec}: {exc}") from None
        # merge_models lists both models' opset imports; one entry per domain is enough.
        seen: dict[str, int] = {}
        for entry in merged.opset_import:
            seen.setdefault(entry.domain, entry.version)
        del merged.opset_import[:]
        merged.opset_import.extend(helper.make_opsetid(d, v) for d, v in seen.items())
        return merged

    def _verify_size(self, image: _ImageInput) -> tuple[int, int]:
        h = image.height.dim_value if image.height.HasField("dim_value") else VERIFY_SIDE_PX
        w = image.width.dim_value if image.width.HasField("dim_value") else VERIFY_SIDE_PX
        return h, w

    def _verify(
        self, original: Path, wrapped: Path, image: _ImageInput, size: tuple[int, int]
    ) -> tuple[float, float]:
        """Run both models on a photograph: the wrapped one on the camera image, the original on
        the same image normalized by hand in numpy. (max abs err, tolerance) of the worst output.
        """
        import onnxruntime as ort

        from common.partition import ort_reason

        photo = _photograph(size)  # RGB
        camera = photo if self.camera_order is ChannelOrder.RGB else photo[:, :, ::-1]
        levels = photo.astype(np.float32) / np.float32(PIXEL_MAX)
        x: np.ndarray = (levels - np.array(self.mean, np.float32)) / np.array(self.std, np.float32)
        if self.layout is Layout.NCHW:
            x = x.transpose(2, 0, 1)
        by_hand = x[None].astype(helper.tensor_dtype_to_np_dtype(image.elem_type))
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        results = []
        for which, path, feed in (
            ("original", original, by_hand),
            ("wrapped", wrapped, camera[None]),
        ):
            try:
                session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
                names = [o.name for o in session.get_outputs()]
                values = session.run(names, {image.name: np.ascontiguousarray(feed)})
            except Exception as exc:
                raise UserError(
                    f"onnxruntime cannot run the {which} model: {ort_reason(exc)}"
                ) from None
            results.append(dict(zip(names, values, strict=True)))
        reference, got = results
        checks = [_compare(n, np.asarray(v), np.asarray(got[n])) for n, v in reference.items()]
        return max(checks, default=(0.0, 0.0))


def _compare(name: str, ref: np.ndarray, got: np.ndarray) -> tuple[float, float]:
    """(max abs err, tolerance) of one output; UserError when it is out of tolerance."""
    if ref.shape != got.shape or ref.dtype != got.dtype:
        raise UserError(
            f"output {name!r}: the wrapped model gives {got.dtype}{list(got.shape)}, the "
            f"original {ref.dtype}{list(ref.shape)}"
        )
    if ref.size == 0:
        return 0.0, 0.0
    err = float(np.max(np.abs(ref.astype(np.float64) - got.astype(np.float64))))
    bound = PREP_RTOL * float(np.max(np.abs(ref))) if ref.dtype.kind in "fc" else 0.0
    if not err <= bound:
        raise UserError(
            f"output {name!r} of the wrapped model differs from the original fed the same "
            f"normalized photograph by {err:.3g} (tolerance {bound:.3g} = {PREP_RTOL:g} × the "
            "output's largest magnitude); nothing written"
        )
    return err, bound


def _photograph(size: tuple[int, int]) -> np.ndarray:
    """scikit-image's astronaut (RGB, 512×512, shipped with the package) resized to H×W."""
    import cv2

    from common.extras import Extra, require

    data = require("skimage.data", Extra.DATA, "the verification photograph")
    photo = data.astronaut()
    h, w = size
    shrink = h < photo.shape[0] or w < photo.shape[1]
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return np.ascontiguousarray(cv2.resize(photo, (w, h), interpolation=interpolation))


def _free_prefix(model: onnx.ModelProto) -> str:
    """FRONT_END_PREFIX, or a numbered variant when the model already uses it."""
    names = {t.name for t in model.graph.initializer} | {vi.name for vi in model.graph.value_info}
    for node in model.graph.node:
        names.update(node.input)
        names.update(node.output)
        names.add(node.name)
    prefix, n = FRONT_END_PREFIX, 0
    while any(name.startswith(prefix) for name in names):
        n += 1
        prefix = f"prep{n}/"
    return prefix


def _value_info(
    name: str, elem_type: int, dims: list[onnx.TensorShapeProto.Dimension]
) -> onnx.ValueInfoProto:
    vi = helper.make_tensor_value_info(name, elem_type, None)
    shape = vi.type.tensor_type.shape
    for d in dims:
        shape.dim.add().CopyFrom(d)
    return vi


def _fixed(d: onnx.TensorShapeProto.Dimension) -> int:
    """A dimension's fixed size, 0 when it is dynamic."""
    return d.dim_value if d.HasField("dim_value") else 0


def _dim_value(d: onnx.TensorShapeProto.Dimension) -> int | str:
    return d.dim_value if d.HasField("dim_value") else (d.dim_param or "?")


def _dims(vi: onnx.ValueInfoProto) -> list[int | str]:
    return [_dim_value(d) for d in vi.type.tensor_type.shape.dim]
