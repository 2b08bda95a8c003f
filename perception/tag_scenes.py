"""Synthetic camera frames of AprilTag 36h11 tags at known poses, for checking a detector's
poses against the truth (the tests, `benchmarks/apriltag_pose.py`) without a camera or a download.

The tag's bits come from OpenCV (`cv2.aruco.generateImageMarker`), printed black on white paper
with a one-cell white margin, as AprilTag's own PDFs are. Its four outer corners are projected
with the true pose and intrinsics (`cv2.projectPoints`) and the printed tag is warped onto them
(`cv2.warpPerspective`) over a background: a photograph (`common.photos`, scikit-image's, so a
real scene's edges and texture surround the tag) or a plain grey. The warp runs at `SUPERSAMPLE`
times the frame's resolution and is then area-averaged down, so the tag's edges are anti-aliased
the way a lens and a sensor's pixels blur them, not stair-stepped.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from perception.tag_edges import TAG_CELLS

MARGIN_CELLS = 1
"""White paper around the black square, in cells."""
CELL_PX = 32
"""Texture pixels per cell of the printed tag: a texture pixel covers at most a frame pixel for
a printed sheet (tag and margin, 10 cells) up to 320 px across: a 0.16 m tag from 0.38 m away
at fx = 600."""
SUPERSAMPLE = 4
PAPER_WHITE = 235
INK_BLACK = 25


@dataclass(frozen=True)
class TagPose:
    """A tag's pose in the camera frame (AprilTag's convention: the tag frame's origin at the
    tag's centre, x to the right and y down as printed, z into the tag), as a rotation vector
    and a translation in metres."""

    rvec: tuple[float, float, float]
    tvec: tuple[float, float, float]

    @property
    def rotation(self) -> np.ndarray:
        return cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64))[0]

    @property
    def translation(self) -> np.ndarray:
        return np.asarray(self.tvec, dtype=np.float64)


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def tag_corners_3d(size_m: float) -> np.ndarray:
    """The black square's outer corners in the tag frame (x right, y down): top-left,
    top-right, bottom-right, bottom-left as printed."""
    h = size_m / 2
    return np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])


def project_corners(pose: TagPose, size_m: float, k: np.ndarray) -> np.ndarray:
    """The tag's corners in the image, pixels (x, y), 4x2 float64, in `tag_corners_3d`'s order."""
    pts, _ = cv2.projectPoints(
        tag_corners_3d(size_m),
        np.asarray(pose.rvec, dtype=np.float64),
        np.asarray(pose.tvec, dtype=np.float64),
        k,
        None,
    )
    return pts.reshape(4, 2)


@functools.cache
def printed_tag(tag_id: int) -> np.ndarray:
    """The tag as printed: uint8 grey, the black square and its white margin, `CELL_PX` per cell
    (read-only, made once per id)."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    bits = cv2.aruco.generateImageMarker(dictionary, tag_id, TAG_CELLS * CELL_PX)
    tag = np.where(bits > 127, PAPER_WHITE, INK_BLACK).astype(np.uint8)
    m = MARGIN_CELLS * CELL_PX
    sheet = cv2.copyMakeBorder(tag, m, m, m, m, cv2.BORDER_CONSTANT, value=PAPER_WHITE)
    sheet.setflags(write=False)
    return sheet


def background(height: int, width: int, photo: str | None = "astronaut") -> np.ndarray:
    """uint8 RGB `height`x`width`: a photograph of `common.photos` (scikit-image's) scaled to
    fill it, or a plain mid grey when `photo` is None."""
    if photo is None:
        return np.full((height, width, 3), 128, dtype=np.uint8)
    from common.photos import photo_bgr

    rgb = cv2.cvtColor(photo_bgr(photo), cv2.COLOR_BGR2RGB)
    # Scaled to cover the frame without distortion, then the centre cut out.
    scale = max(height / rgb.shape[0], width / rgb.shape[1])
    size = (max(width, round(rgb.shape[1] * scale)), max(height, round(rgb.shape[0] * scale)))
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    scaled = cv2.resize(rgb, size, interpolation=interpolation)
    y, x = (scaled.shape[0] - height) // 2, (scaled.shape[1] - width) // 2
    return np.ascontiguousarray(scaled[y : y + height, x : x + width])


def render(
    scene: np.ndarray,
    tags: list[tuple[int, TagPose]],
    size_m: float,
    k: np.ndarray,
    blur_sigma_px: float = 0.0,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """`scene` (uint8 HxWx3 RGB, not changed) with each (id, pose) of `tags` drawn on it, then
    a Gaussian blur of `blur_sigma_px` (a lens's) and Gaussian pixel noise of `noise_sigma` grey
    levels (a sensor's, seeded by `seed`); uint8 HxWx3 RGB."""
    out: np.ndarray = scene.astype(np.float32)
    for tag_id, pose in tags:
        _draw(out, printed_tag(tag_id), project_corners(pose, size_m, k))
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        rng = np.random.default_rng(seed)
        out = out + rng.normal(0.0, noise_sigma, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _draw(frame: np.ndarray, texture: np.ndarray, corners: np.ndarray) -> None:
    """Paint `texture` (the printed tag) into `frame` (float32 HxWx3, in place) with its black
    square's corners on `corners`: warped at SUPERSAMPLE times the resolution over the tag's
    bounding box only, then area-averaged to the tag's coverage and colour of each pixel, so the
    pixels it does not cover are left exactly as they were."""
    h, w = frame.shape[:2]
    s = SUPERSAMPLE
    m, side = MARGIN_CELLS * CELL_PX, TAG_CELLS * CELL_PX
    # The black square's outer edges in the texture: pixel centres are at integers, so the
    # square's edge lies half a pixel outside its first and last pixels.
    lo, hi = m - 0.5, m + side - 0.5
    src = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], dtype=np.float32)
    # The same corners at SUPERSAMPLE: a pixel centre i is at (i + 0.5) s - 0.5 there, so that
    # each pixel is the mean of an s x s block.
    dst = ((np.asarray(corners) + 0.5) * s - 0.5).astype(np.float32)
    homography = cv2.getPerspectiveTransform(src, dst)
    # The printed sheet's bounding box in the frame, in whole pixels.
    edge = texture.shape[0] - 0.5
    sheet = np.array([[[-0.5, -0.5]], [[edge, -0.5]], [[edge, edge]], [[-0.5, edge]]])
    big = cv2.perspectiveTransform(sheet, homography).reshape(4, 2)
    x0, y0 = np.maximum(np.floor((big.min(axis=0) + 0.5) / s) - 1, 0).astype(int)
    x1, y1 = np.minimum(np.ceil((big.max(axis=0) + 0.5) / s) + 1, [w, h]).astype(int)
    if x1 <= x0 or y1 <= y0:
        return
    shift = np.array([[1.0, 0.0, -x0 * s], [0.0, 1.0, -y0 * s], [0.0, 0.0, 1.0]])
    size = ((x1 - x0) * s, (y1 - y0) * s)
    # Warped with a 0 border, the texture comes out already weighted by its coverage.
    paint = cv2.warpPerspective(
        texture.astype(np.float32), shift @ homography, size, flags=cv2.INTER_LINEAR
    )
    cover = cv2.warpPerspective(
        np.ones(texture.shape, dtype=np.float32), shift @ homography, size, flags=cv2.INTER_LINEAR
    )
    paint = cv2.resize(paint, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    cover = cv2.resize(cover, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    roi = frame[y0:y1, x0:x1]
    roi *= 1.0 - cover[..., None]
    roi += paint[..., None]


def random_pose(
    rng: np.random.Generator,
    size_m: float,
    k: np.ndarray,
    height: int,
    width: int,
    distance_m: tuple[float, float] = (0.5, 2.0),
    max_tilt_deg: float = 50.0,
    margin_px: float = 10.0,
) -> TagPose:
    """A pose of a tag of `size_m` wholly in a `height` x `width` view, its white margin too
    (the printed sheet's corners at least `margin_px` inside): its centre at a depth uniform in
    `distance_m`, anywhere in the view; any roll, and tilted from facing the camera by up to
    `max_tilt_deg` about an axis in the tag's plane in any direction."""
    sheet_m = size_m * (TAG_CELLS + 2 * MARGIN_CELLS) / TAG_CELLS
    while True:
        z = rng.uniform(*distance_m)
        u, v = rng.uniform(0, width), rng.uniform(0, height)
        x, y = (u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z
        tilt = np.deg2rad(rng.uniform(0.0, max_tilt_deg))
        direction = rng.uniform(0.0, 2 * np.pi)
        roll = cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))[0]
        tilt_axis = np.array([np.cos(direction), np.sin(direction), 0.0])
        rotation = cv2.Rodrigues(tilt * tilt_axis)[0] @ roll
        rvec = cv2.Rodrigues(rotation)[0].reshape(3)
        pose = TagPose((float(rvec[0]), float(rvec[1]), float(rvec[2])), (x, y, z))
        corners = project_corners(pose, sheet_m, k)
        inside = (corners >= margin_px).all() and (
            corners <= np.array([width - 1 - margin_px, height - 1 - margin_px])
        ).all()
        if inside:
            return pose


def pose_errors(found: np.ndarray, truth: TagPose) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees) of a found pose (tx, ty, tz,
    qx, qy, qz, qw) against the truth: the distance between the centres and the angle of the
    rotation taking one orientation to the other."""
    found = np.asarray(found, dtype=np.float64)
    translation = float(np.linalg.norm(found[:3] - truth.translation))
    q = found[3:] / np.linalg.norm(found[3:])
    t = _quaternion_of(truth.rotation)
    # The rotation from the truth to the found one, conj(t) * q; its angle by atan2, which
    # (unlike acos of a dot product) resolves the hundredths of a degree float32 poses carry.
    vector = t[3] * q[:3] - q[3] * t[:3] - np.cross(t[:3], q[:3])
    scalar = t[3] * q[3] + float(np.dot(t[:3], q[:3]))
    angle = 2 * np.arctan2(float(np.linalg.norm(vector)), abs(scalar))
    return translation, float(np.rad2deg(angle))


def _quaternion_of(rotation: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(rotation)[0].reshape(3)
    angle = float(np.linalg.norm(rvec))
    axis = rvec / angle if angle > 0 else np.zeros(3)
    return np.append(axis * np.sin(angle / 2), np.cos(angle / 2))
