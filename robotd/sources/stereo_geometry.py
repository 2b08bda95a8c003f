"""A stereo camera's geometry as its CameraInfos give it, against the one the model was built for.

zoo:stereo is built for one camera (fleet.yaml `nav: camera:`, the same file and digest on the
robot and every deployment), and states it in its metadata `nav.camera`: fx, baseline, cx, cy
(pixels of the model's input), height and forward offset (m). A ROS 2 stereo source learns its
camera's geometry from the CameraInfos (`robotd.sources.ros2_stereo.stereo_geometry`). When the
two disagree by more than `GEOMETRY_TOLERANCE` on fx or the baseline, every distance the model
computes is off by the ratio of fx·B (depth = fx·B/d): `mismatch_warning` says so in one
warning with the `nav: camera:` lines that build the model for this camera. The robot cannot
rebuild the model alone (its deployments must hold the same digest): it keeps serving.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from common.errors import UserError

MODEL_CAMERA_KEY = "nav.camera"
"""The model metadata naming the camera it was built for (written by `nav.stereo_graph`)."""
GEOMETRY_TOLERANCE = 0.02
"""Relative difference on fx or the baseline past which the camera is not the model's."""


@dataclass(frozen=True)
class StereoGeometry:
    """A rectified pair's geometry in pixels of the model's view: focal length, principal
    point, baseline (m)."""

    fx_px: float
    cx_px: float
    cy_px: float
    baseline_m: float


@dataclass(frozen=True)
class ModelCamera:
    """The camera a stereo model was built for, as its metadata `nav.camera` states it."""

    fx_px: float
    baseline_m: float
    cx_px: float
    cy_px: float
    height_m: float
    forward_m: float

    @classmethod
    def parse(cls, text: str) -> ModelCamera:
        """`nav.camera`'s value: six numbers joined by commas; UserError otherwise."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            values = []
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise UserError(
                f"model metadata {MODEL_CAMERA_KEY} is {text!r}; expected six numbers: fx, "
                "baseline, cx, cy, height, forward"
            )
        return cls(*values)


def model_camera(path: str | Path) -> ModelCamera | None:
    """The camera the ONNX model at `path` was built for; None when its metadata names none (a
    stereo model not from the zoo)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    for prop in model.metadata_props:
        if prop.key == MODEL_CAMERA_KEY:
            return ModelCamera.parse(prop.value)
    return None


def hfov_deg(fx_px: float, width: int) -> float:
    """The horizontal field of view of an image `width` pixels wide with focal length fx."""
    return math.degrees(2 * math.atan(width / (2 * fx_px)))


def mismatch_warning(
    seen: StereoGeometry, built: ModelCamera, *, height: int, width: int
) -> str | None:
    """The warning for a camera (`seen`, in the model's `height`×`width` view) that is not the
    one the model was built for, or None when fx and the baseline agree within
    `GEOMETRY_TOLERANCE`. It names both, the factor every distance is off by, and the
    `nav: camera:` lines (hfov_deg from the camera's fx in the model view, baseline_m from its
    right CameraInfo, height_m the model's: the CameraInfo does not know it)."""
    fx_off = abs(seen.fx_px / built.fx_px - 1)
    baseline_off = abs(seen.baseline_m / built.baseline_m - 1)
    if fx_off <= GEOMETRY_TOLERANCE and baseline_off <= GEOMETRY_TOLERANCE:
        return None
    ratio = (seen.fx_px * seen.baseline_m) / (built.fx_px * built.baseline_m)
    stanza = "\n".join(
        (
            "nav:",
            "  camera:",
            f"    baseline_m: {seen.baseline_m:.4g}",
            f"    hfov_deg: {hfov_deg(seen.fx_px, width):.2f}",
            f"    height_m: {built.height_m:g}",
        )
    )
    return (
        f"the camera's CameraInfo geometry (fx {seen.fx_px:.1f} px in the model view "
        f"{width}x{height}, hfov {hfov_deg(seen.fx_px, width):.1f} deg, baseline "
        f"{seen.baseline_m:.4f} m) is not the one the model was built for (fx "
        f"{built.fx_px:.1f} px, hfov {hfov_deg(built.fx_px, width):.1f} deg, baseline "
        f"{built.baseline_m:.4f} m): the true distances are {ratio:.2f}x those the model "
        "computes (depth = fx*B/d). Serving on with the model's geometry. To build zoo:stereo "
        "for this camera, put these lines in the fleet file and restart the robot and its "
        f"deployments (they must hold the same model):\n{stanza}"
    )
