"""AprilTag 36h11 tags and their 6-DoF poses in the camera frame: the handler
`perception.apriltag:detect` (FogROS2-LS's own workload, AprilTag pose estimation on 640x480).

    services:
      tags: {handler: "perception.apriltag:detect", input_shape: [3, 480, 640],
             params: {size_m: 0.16, fx: 600, fy: 600, cx: 320, cy: 240}}

Detection is OpenCV's ArUco detector with the AprilTag 36h11 dictionary, in its faster
"ArUco 3" mode and without OpenCV's corner refinement; the corners are then refined to sub-pixel
from the tag's four sides (`perception.tag_edges`), and the pose is `cv2.solvePnP` with
SOLVEPNP_IPPE_SQUARE (the planar-square solver) on them. `benchmarks/apriltag_pose.py` measures
the accuracy on rendered tags and the rate; docs/services.md has the figures.

Params (the service's `params`, keyword arguments; anything else is an error naming the known
ones): `size_m`, required, the side of the tag's black square in metres (the outer edge of the
black border, as AprilTag measures a tag); the pinhole intrinsics of the image as the handler
sees it (after the resize to `input_shape`), in pixels: `fx`, `fy` (default: the other one, or
both the image's width, a 53° horizontal field of view), `cx`, `cy` (default: the image's
centre, (W-1)/2 and (H-1)/2, with pixel centres at integers as OpenCV has them). The image must
be rectified (no lens distortion).

Outputs, one row per tag found, sorted by id (N may be 0; names and dtypes never change):

- `ids`: int32 [N], the tag's 36h11 id.
- `poses`: float32 [N, 7], (tx, ty, tz, qx, qy, qz, qw): the tag's centre in the camera frame
  in metres and the tag frame's rotation as a unit quaternion with qw >= 0. Camera frame as
  OpenCV's (x right, y down, z forward); tag frame as the AprilTag library's (origin at the tag's
  centre, x right and y down as the tag is printed, z into the tag), so a tag squarely facing the
  camera, upright, has the identity rotation (0, 0, 0, 1).
- `corners`: float32 [N, 4, 2], the black square's corners in the image, pixels (x, y): top-left,
  top-right, bottom-right, bottom-left as the tag is printed (clockwise in the image).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any

import cv2
import numpy as np

from common.handlers import HANDLER_INPUT
from perception.tag_edges import refine_corners

KNOWN_PARAMS = ("size_m", "fx", "fy", "cx", "cy")
DICTIONARY = cv2.aruco.DICT_APRILTAG_36h11


@dataclass(frozen=True)
class TagParams:
    """The handler's params, checked: the tag's size and the image's pinhole intrinsics."""

    size_m: float
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def parse(cls, params: Mapping[str, Any], height: int, width: int) -> TagParams:
        """`params` checked against an image of `height` x `width`; ValueError naming the
        param and what it must be."""
        unknown = sorted(set(params) - set(KNOWN_PARAMS))
        if unknown:
            raise ValueError(
                f"apriltag: unknown params {', '.join(unknown)} (known: {', '.join(KNOWN_PARAMS)})"
            )
        if "size_m" not in params:
            raise ValueError(
                "apriltag: params.size_m is required: the side of the tag's black square, metres"
            )
        size_m = _number(params, "size_m", positive=True)
        fx = _number(params, "fx", positive=True) if "fx" in params else None
        fy = _number(params, "fy", positive=True) if "fy" in params else None
        focal_x = fx if fx is not None else (fy if fy is not None else float(width))
        focal_y = fy if fy is not None else focal_x
        cx = _number(params, "cx") if "cx" in params else (width - 1) / 2
        cy = _number(params, "cy") if "cy" in params else (height - 1) / 2
        return cls(size_m, focal_x, focal_y, cx, cy)

    def camera_matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def _number(params: Mapping[str, Any], name: str, positive: bool = False) -> float:
    value = params[name]
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(float(value)):
        raise ValueError(f"apriltag: params.{name} must be a number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"apriltag: params.{name} must be > 0, got {value!r}")
    return float(value)


def _gray(inputs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The input image as uint8 HxW grey; ValueError when it is not uint8 1xHxWx3."""
    image = inputs.get(HANDLER_INPUT)
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 4:
        described = (
            f"{image.dtype} {list(image.shape)}"
            if isinstance(image, np.ndarray)
            else type(image).__name__
        )
        raise ValueError(
            f"apriltag: input {HANDLER_INPUT!r} must be uint8 1xHxWx3 RGB, got {described}"
        )
    if image.shape[0] != 1 or image.shape[3] != 3:
        raise ValueError(
            f"apriltag: input {HANDLER_INPUT!r} must be uint8 1xHxWx3 RGB, got {list(image.shape)}"
        )
    return cv2.cvtColor(image[0], cv2.COLOR_RGB2GRAY)


_local = threading.local()


def _detector() -> cv2.aruco.ArucoDetector:
    """This thread's detector (a deployment calls handlers from several worker threads; each
    gets its own rather than sharing one OpenCV object)."""
    detector = getattr(_local, "detector", None)
    if detector is None:
        parameters = cv2.aruco.DetectorParameters()
        # ArUco 3's candidate search: less than half the time of the classic one on 640x480
        # (benchmarks/apriltag_pose.py has both). OpenCV's corner refinement is off: tag_edges
        # refines from the sides, more accurately and in less time (the same benchmark).
        parameters.useAruco3Detection = True
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        detector = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(DICTIONARY), parameters
        )
        _local.detector = detector
    return detector


def _ippe_object_points(size_m: float) -> np.ndarray:
    """The square SOLVEPNP_IPPE_SQUARE requires, (-s/2, s/2), (s/2, s/2), (s/2, -s/2),
    (-s/2, -s/2): in our tag frame (y down) the bottom-left, bottom-right, top-right and
    top-left corners, so the image corners go in as [3, 2, 1, 0] and the pose comes out in the
    tag frame of the module docstring."""
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def quaternion(rvec: np.ndarray) -> np.ndarray:
    """A rotation vector (axis times angle, radians) as (qx, qy, qz, qw) with qw >= 0."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(r))
    # sin(angle/2) / angle, finite at 0 (np.sinc(x) is sin(pi x) / (pi x)).
    q = np.append(r * 0.5 * np.sinc(angle / (2 * np.pi)), math.cos(angle / 2))
    return q if q[3] >= 0 else -q


def solve_pose(corners: np.ndarray, tag: TagParams) -> np.ndarray | None:
    """The pose (tx, ty, tz, qx, qy, qz, qw), float64, of a tag whose black square's corners
    are `corners` (4x2 pixels, top-left, top-right, bottom-right, bottom-left as printed); None
    when the solver finds none."""
    ok, rvec, tvec = cv2.solvePnP(
        _ippe_object_points(tag.size_m),
        np.asarray(corners, dtype=np.float64)[[3, 2, 1, 0]],
        tag.camera_matrix(),
        None,
        flags=cv2.SOLVEPNP_IPPE_SQUARE,
    )
    if not ok:
        return None
    return np.concatenate([np.asarray(tvec, dtype=np.float64).reshape(3), quaternion(rvec)])


def detect(inputs: Mapping[str, np.ndarray], **params: Any) -> dict[str, np.ndarray]:
    """AprilTag 36h11 tags in `inputs["image"]` and their poses (module docstring: params and
    outputs)."""
    gray = _gray(inputs)
    tag = TagParams.parse(params, *gray.shape)
    found_corners, found_ids, _ = _detector().detectMarkers(gray)
    ids: list[int] = []
    poses: list[np.ndarray] = []
    corners: list[np.ndarray] = []
    flat_ids = np.asarray(found_ids if found_ids is not None else [], dtype=np.int64).reshape(-1)
    for index in np.argsort(flat_ids, kind="stable"):
        refined = refine_corners(gray, np.asarray(found_corners[index]).reshape(4, 2))
        pose = solve_pose(refined, tag)
        if pose is not None:
            ids.append(int(flat_ids[index]))
            poses.append(pose)
            corners.append(refined)
    return outputs(ids, poses, corners)


def outputs(
    ids: list[int], poses: list[np.ndarray], corners: list[np.ndarray]
) -> dict[str, np.ndarray]:
    """The handler's outputs for these tags, with their fixed names, dtypes and shapes (N may
    be 0)."""
    return {
        "ids": np.asarray(ids, dtype=np.int32).reshape(-1),
        "poses": np.asarray(poses, dtype=np.float32).reshape(-1, 7),
        "corners": np.asarray(corners, dtype=np.float32).reshape(-1, 4, 2),
    }
