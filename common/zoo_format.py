"""The zoo's conventions, shared by the zoo's index (`common.zoo`) and its networks
(`common.zoo_nets`): tensor names, opset, format version, seed, the camera input and its
normalization. Apart from both so that neither imports the other back.
"""

from __future__ import annotations

ZOO_INPUT_NAME = "input"
ZOO_OUTPUT_NAME = "logits"
ZOO_OPSET = 17
# Bumped whenever a built model changes for the same name and shape (2: uint8 image input;
# 3: written with onnx.helper instead of exported from torch: new weights and tensor names).
ZOO_FORMAT = 3
ZOO_SEED = 0
NUM_CLASSES = 1000
ZOO_INPUT_DTYPE = "uint8"
# What the robot feeds a 3-channel uint8 input (common.image_input.InputAdapter): RGB. "bgr" would
# reorder the channels in the front end.
CAMERA_ORDER = "rgb"
# ImageNet statistics in RGB order (torchvision's), for 3 channels; other channel counts use
# their averages for every channel (a grey image, typically).
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)
GREY_MEAN = 0.449
GREY_STD = 0.226
PIXEL_MAX = 255.0


def zoo_normalization(channels: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per-channel (mean, std) of the zoo's front end, in the model's channel order (RGB)."""
    if channels == 3:
        return IMAGENET_MEAN, IMAGENET_STD
    return (GREY_MEAN,) * channels, (GREY_STD,) * channels


def file_input_shape(shape: tuple[int, int, int]) -> tuple[int, int, int, int]:
    """The exported file's input shape for zoo shape (C, H, W): the camera image, 1×H×W×C."""
    c, h, w = shape
    return (1, h, w, c)
