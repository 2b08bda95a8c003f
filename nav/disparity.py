"""The disparity of a rectified stereo pair, from image files (``elasticfog nav disparity``).

Contract: float32 H×W, the pair's own size, disparity in pixels of the left image (a point at
column u of the left image is at u − d in the right one), NaN where no disparity passed the
checks. The graph is the zoo model's stages up to ``disparity`` (:mod:`nav.stereo_graph`) with
a symbolic image size, so one session serves any pair of a run.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from common.errors import UserError
from nav.camera import CameraModel
from nav.stereo_graph import LEFT_INPUT, RIGHT_INPUT, Stage, StereoPipeline, build_model
from nav.stereo_params import StereoParams

# The camera does not enter the disparity stages; any model fills the pipeline's slot.
_UNUSED_CAMERA = CameraModel(fx_px=1.0, baseline_m=1.0, cx_px=0.0, cy_px=0.0)


@dataclass(frozen=True)
class DisparityResult:
    disparity: np.ndarray
    seconds: float

    @property
    def valid_share(self) -> float:
        return float(np.isfinite(self.disparity).mean())


class DisparityRunner:
    """One onnxruntime session of the disparity stages for a parameter set."""

    def __init__(self, params: StereoParams, threads: int | None = None) -> None:
        self.params = params
        model = build_model(StereoPipeline(params, _UNUSED_CAMERA), last=Stage.DISPARITY)
        options = ort.SessionOptions()
        options.log_severity_level = 3
        if threads is not None:
            if threads < 1:
                raise UserError(f"--threads must be a positive integer, got {threads}")
            options.intra_op_num_threads = threads
        self.session = ort.InferenceSession(
            model.SerializeToString(), options, providers=["CPUExecutionProvider"]
        )

    def __call__(self, left_rgb: np.ndarray, right_rgb: np.ndarray) -> DisparityResult:
        """Disparity of an RGB uint8 H×W×3 pair (checked: same size, range fits)."""
        if left_rgb.shape != right_rgb.shape:
            raise UserError(
                f"the left image is {_size(left_rgb)} but the right one is {_size(right_rgb)}: "
                "a rectified pair has one size"
            )
        if left_rgb.ndim != 3 or left_rgb.shape[2] != 3 or left_rgb.dtype != np.uint8:
            raise UserError(f"images must be uint8 H×W×3, got {left_rgb.dtype} {left_rgb.shape}")
        self.params.check_image(*left_rgb.shape[:2])
        feeds = {LEFT_INPUT: left_rgb[None], RIGHT_INPUT: right_rgb[None]}
        start = time.perf_counter()
        (disparity,) = self.session.run([Stage.DISPARITY.value], feeds)
        seconds = time.perf_counter() - start
        return DisparityResult(np.ascontiguousarray(disparity[0, 0], dtype=np.float32), seconds)


@functools.cache
def runner(max_disparity: int, threads: int | None = None) -> DisparityRunner:
    """A shared runner per disparity range (sessions take a moment to build)."""
    return DisparityRunner(StereoParams(max_disparity), threads)


def read_rgb(path: Path, which: str) -> np.ndarray:
    """An image file as uint8 RGB H×W×3 (grey files are expanded); UserError naming the file."""
    if not path.exists():
        raise UserError(f"{which} image not found: {path}")
    if not path.is_file():
        raise UserError(f"{which} image is not a file: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise UserError(f"{which} image {path} is not an image OpenCV can read")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def disparity_files(
    left: Path, right: Path, max_disparity: int, out: Path, threads: int | None = None
) -> DisparityResult:
    """Disparity of the pair in two image files, written to ``out`` as a .npy file."""
    params = StereoParams(max_disparity)  # a bad range fails before anything is read
    if out.suffix != ".npy":
        raise UserError(f"--out {out}: the disparity is written as a .npy file (name it *.npy)")
    if not out.parent.is_dir():
        raise UserError(f"--out {out}: directory {out.parent} does not exist")
    left_rgb, right_rgb = read_rgb(left, "left"), read_rgb(right, "right")
    if left_rgb.shape != right_rgb.shape:
        raise UserError(
            f"left image {left} is {_size(left_rgb)} but right image {right} is "
            f"{_size(right_rgb)}: a rectified pair has one size"
        )
    params.check_image(*left_rgb.shape[:2])
    result = runner(max_disparity, threads)(left_rgb, right_rgb)
    with open(out, "wb") as f:  # np.save on a path would add .npy to any other name
        np.save(f, result.disparity)
    return result


def _size(image: np.ndarray) -> str:
    return f"{image.shape[1]}x{image.shape[0]}"
