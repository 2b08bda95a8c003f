"""The dense service of `bench services`: a small segmentation-like network, built as ONNX in code.

The zoo's networks are classifiers: what they answer is 1000 numbers, and past their first
layers every crossing is smaller than the image. A dense model answers per pixel: here class
scores for every pixel of the camera image (float 1xKxHxW, `DENSE_CLASSES` classes), computed by
an encoder at a quarter of the resolution and upsampled back (bilinear `Resize`), like a small
fully convolutional segmentation network. Every feature map between its layers is larger than
the raw image (the first is 48 channels at half the resolution, as float: 16 times its bytes),
so the only cheap crossing is cut 0, and its answer (1.2 MB at 320x240) is 300 times a
classifier's.

It takes the zoo's camera image (uint8 1xHxWx3, `common.zoo_nets.NetBuilder.front_end`) and
is written once per shape into the bench's work folder (`write_dense_model`); weights are the
zoo's seeded draws (no training, no downloads): the graph, sizes and times are what matter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from common.zoo_format import ZOO_INPUT_NAME, file_input_shape
from common.zoo_nets import Act, NetBuilder

DENSE_CLASSES = 4
"""Classes scored per pixel: the answer is DENSE_CLASSES x H x W float32."""
DENSE_OUTPUT = "scores"
ENCODER_WIDTHS = (48, 96, 128, 128, 128)
"""Channels of the encoder's 3x3 convolutions: stride 2, stride 2, then three at a quarter of
the resolution (2.2 GMAC at 320x240: about 45 ms on one core of the testbed host, twice the
classifier's MobileNetV2 at 320x240)."""
UPSAMPLE = 4


def dense_model(shape: tuple[int, int, int]) -> onnx.ModelProto:
    """The network for the camera image of shape (C, H, W), checked by `onnx.checker`; H and W
    must be multiples of UPSAMPLE (the answer has the image's size)."""
    channels, height, width = shape
    if height % UPSAMPLE or width % UPSAMPLE:
        raise ValueError(f"image {height}x{width}: both sides must be multiples of {UPSAMPLE}")
    b = NetBuilder()
    x = b.front_end(ZOO_INPUT_NAME, channels)
    cin = channels
    for i, cout in enumerate(ENCODER_WIDTHS):
        x = b.conv_bn(x, f"enc{i}", cin, cout, 3, stride=2 if i < 2 else 1)
        cin = cout
    x = b.conv_bn(x, "classes", cin, DENSE_CLASSES, 1, act=Act.NONE)
    scales = b.const("up.scales", np.asarray([1, 1, UPSAMPLE, UPSAMPLE], np.float32))
    b.node("Resize", [x, "", scales], DENSE_OUTPUT, mode="linear")
    image = helper.make_tensor_value_info(
        ZOO_INPUT_NAME, TensorProto.UINT8, list(file_input_shape(shape))
    )
    out = helper.make_tensor_value_info(
        DENSE_OUTPUT, TensorProto.FLOAT, [1, DENSE_CLASSES, height, width]
    )
    return b.model("bench_dense", [image], [out])


def write_dense_model(directory: Path, shape: tuple[int, int, int]) -> Path:
    """`directory/dense-CxHxW.onnx`, written unless it is there; its path."""
    path = directory / f"dense-{'x'.join(map(str, shape))}.onnx"
    if not path.exists():
        directory.mkdir(parents=True, exist_ok=True)
        onnx.save(dense_model(shape), path)
    return path
