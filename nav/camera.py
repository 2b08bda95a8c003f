"""The stereo camera model and the ground-plane frame the assistant works in.

Frame (the paper's Fig. 3, on the floor): origin O at the centre of the driven wheel axle,
``x`` to the right, ``y`` forward, ``z`` up. The camera is level (optical axis along ``y``),
``forward_m`` ahead of the axle and ``height_m`` above the floor; its pixel ``(u, v)`` with
disparity ``d`` (rectified pair, pixels of the left image) is the point

    x = (u − cx)·b/d,   y = fx·b/d + forward_m,   z = height_m − (v − cy)·b/d

(the camera's own y axis points down, hence the minus). :func:`points_from_disparity` is the
numpy reference of the ONNX ``points`` stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.defaults import (
    DEFAULT_STEREO_BASELINE_M,
    DEFAULT_STEREO_HEIGHT_M,
    DEFAULT_STEREO_HFOV_DEG,
)
from common.errors import UserError

# A common small stereo camera: 60° horizontal field of view and a 6 cm baseline (the
# disparity range then covers obstacles from about half a metre, see nav.stereo_params). The
# fleet file's `nav: camera:` section (defaults in common.defaults) says another.
DEFAULT_HFOV_DEG = DEFAULT_STEREO_HFOV_DEG
DEFAULT_BASELINE_M = DEFAULT_STEREO_BASELINE_M
# Mounted on a small indoor robot (the paper's Erratic is about 0.4 m tall).
DEFAULT_HEIGHT_M = DEFAULT_STEREO_HEIGHT_M
DEFAULT_FORWARD_M = 0.10


@dataclass(frozen=True)
class CameraModel:
    """Pinhole model of the rectified left camera and where it sits on the robot."""

    fx_px: float
    baseline_m: float
    cx_px: float
    cy_px: float
    height_m: float = DEFAULT_HEIGHT_M
    forward_m: float = DEFAULT_FORWARD_M

    def __post_init__(self) -> None:
        for name in ("fx_px", "baseline_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise UserError(f"camera {name} must be a positive number, got {value!r}")
        for name in ("cx_px", "cy_px", "height_m", "forward_m"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise UserError(f"camera {name} must be a finite number, got {value!r}")

    @classmethod
    def for_image(
        cls,
        width: int,
        height: int,
        hfov_deg: float = DEFAULT_HFOV_DEG,
        baseline_m: float = DEFAULT_BASELINE_M,
        height_m: float = DEFAULT_HEIGHT_M,
    ) -> CameraModel:
        """The camera at a resolution: the same lens, so fx scales with the width and the
        principal point is the image centre."""
        if width < 1 or height < 1:
            raise UserError(f"image size must be positive, got {width}x{height}")
        if not 0 < hfov_deg < 180:
            raise UserError(f"horizontal field of view must be in (0, 180) degrees: {hfov_deg}")
        fx = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
        return cls(fx, baseline_m, (width - 1) / 2, (height - 1) / 2, height_m)

    def depth_m(self, disparity_px: float) -> float:
        """Distance along the optical axis of a point seen with this disparity."""
        return self.fx_px * self.baseline_m / disparity_px

    def projection(self) -> np.ndarray:
        """3×3 matrix M with [x, y − forward, z − height] = M·[u, v, 1]·(b/d) (see the module
        docstring): the ONNX points stage multiplies by it."""
        return np.array(
            [
                [1.0, 0.0, -self.cx_px],
                [0.0, 0.0, self.fx_px],
                [0.0, -1.0, self.cy_px],
            ]
        )

    def offset(self) -> np.ndarray:
        """The camera centre in the ground frame, [0, forward, height]."""
        return np.array([0.0, self.forward_m, self.height_m])


def points_from_disparity(disparity: np.ndarray, camera: CameraModel) -> np.ndarray:
    """H×W disparity (pixels, NaN or ≤ 0 where there is no point) → H×W×3 points (x, y, z) in
    the ground frame, NaN where there is no point. float64, the reference of the ONNX stage."""
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2:
        raise UserError(f"disparity must be an H×W array, got shape {d.shape}")
    h, w = d.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(d > 0, camera.baseline_m / d, np.nan)
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    x = (u - camera.cx_px) * scale
    y = camera.fx_px * scale + camera.forward_m
    z = camera.height_m - (v - camera.cy_px) * scale
    return np.stack([x, y, z], axis=-1)
