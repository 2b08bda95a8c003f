"""Sub-pixel corners of a detected tag, from its four edges: the step in the image is located
along many short profiles across each side of the black square, a line is fitted to each side,
and the corners are where neighbouring lines meet.

OpenCV's quad detector gives corners to about a pixel (the corners of a polygon fitted to a
thresholded contour). Its own refinements trade speed for accuracy (CORNER_REFINE_APRILTAG, the
AprilTag library's gradient-weighted line fit, roughly doubles the detection time), and
`cv2.cornerSubPix` looks for a saddle point, which a tag's outer corner is not. A side of the
black square is the one long straight step edge of the tag (white paper outside, black border
inside), so a line through a few dozen edge points fixes it to a fraction of a pixel for the cost
of one `cv2.remap` over a few thousand points. The image must be free of lens distortion (a
rectified camera image): the sides are fitted as straight lines.
"""

from __future__ import annotations

import cv2
import numpy as np

TAG_CELLS = 8
"""Cells across a 36h11 tag's black square (6x6 data bits and a one-cell black border)."""
PROFILE_STEP_PX = 0.25
"""Spacing of the samples along a profile across an edge."""
PROFILE_REACH_CELLS = 0.5
"""How far a profile reaches either side of the current edge, in tag cells (a 36h11 tag's black
square is 8 cells across: half a cell stays within the black border and the white margin)."""
MIN_REACH_PX, MAX_REACH_PX = 1.5, 4.0
EDGE_SPAN = (0.12, 0.88)
"""The part of each side that is sampled: the ends are left out, where the profile would cross
the neighbouring side."""
MIN_PROFILES, MAX_PROFILES = 8, 48
"""Profiles per side: about one every 2 px of the side, within these bounds."""
PEAK_HALF_WIDTH_PX = 1.5
"""The gradient is averaged this far either side of its peak (a blurred step's width)."""
ROUNDS = 2
"""Fit rounds: the second starts from the first's corners, so its profiles are centred."""


def refine_corners(gray: np.ndarray, corners: np.ndarray, rounds: int = ROUNDS) -> np.ndarray:
    """The four corners of a dark square on a light ground, refined to sub-pixel: `gray` uint8
    HxW, `corners` 4x2 (x, y) in order around the square (either direction). Returns float64
    4x2 in the same order; the input corners unchanged where a round moves any corner further
    than a profile reaches (an occluded or cut side: the coarse corners are the safer answer)."""
    start = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    current = start
    for _ in range(rounds):
        side = float(np.min(np.linalg.norm(current - np.roll(current, 1, axis=0), axis=1)))
        reach = float(np.clip(side / TAG_CELLS * PROFILE_REACH_CELLS, MIN_REACH_PX, MAX_REACH_PX))
        refined = _one_round(gray, current, side, reach)
        if refined is None or np.max(np.linalg.norm(refined - start, axis=1)) > 2 * reach:
            return start
        current = refined
    return current


def _one_round(
    gray: np.ndarray, corners: np.ndarray, side: float, reach: float
) -> np.ndarray | None:
    """One round over the four sides at once; None when a side yields too few edge points."""
    starts, ends = corners, np.roll(corners, -1, axis=0)
    along = ends - starts
    normals = np.stack([along[:, 1], -along[:, 0]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Outward: away from the square's centre, so the profile runs from black to white.
    outward = np.sign(np.sum(((starts + ends) / 2 - corners.mean(axis=0)) * normals, axis=1))
    normals *= outward[:, None]

    count = int(np.clip(side / 2, MIN_PROFILES, MAX_PROFILES))
    t = np.linspace(*EDGE_SPAN, count)
    offsets = np.arange(-reach, reach + 1e-9, PROFILE_STEP_PX)
    centres = starts[:, None, :] + t[None, :, None] * along[:, None, :]  # 4 x count x 2
    grid = centres[:, :, None, :] + offsets[None, None, :, None] * normals[:, None, None, :]
    flat = grid.reshape(-1, offsets.size, 2).astype(np.float32)
    profiles = cv2.remap(
        gray, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    ).astype(np.float64)

    # The edge along each profile: the gradient's centroid around its peak (dark to light).
    gradient = np.maximum(np.gradient(profiles, axis=1), 0.0)
    peak = np.argmax(gradient, axis=1)
    half = round(PEAK_HALF_WIDTH_PX / PROFILE_STEP_PX)
    window = np.clip(peak[:, None] + np.arange(-half, half + 1)[None, :], 0, offsets.size - 1)
    weights = np.take_along_axis(gradient, window, axis=1)
    total = weights.sum(axis=1)
    found = total > 0
    shift = (weights * offsets[window]).sum(axis=1) / np.where(found, total, 1.0)
    points = (centres.reshape(-1, 2) + shift[:, None] * np.repeat(normals, count, axis=0)).reshape(
        4, count, 2
    )
    found = found.reshape(4, count)

    lines = []
    for k in range(4):
        pts = points[k][found[k]]
        if len(pts) < MIN_PROFILES // 2:
            return None
        vx, vy, x0, y0 = cv2.fitLine(pts.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], dtype=np.float64), np.array([vx, vy], dtype=np.float64)))

    # Corner k is where side k-1 (ending at it) meets side k (starting at it).
    out = np.empty((4, 2))
    for k in range(4):
        (p1, d1), (p2, d2) = lines[k - 1], lines[k]
        system = np.array([d1, -d2]).T
        if abs(np.linalg.det(system)) < 1e-6:
            return None
        s = np.linalg.solve(system, p2 - p1)
        out[k] = p1 + s[0] * d1
    return out
