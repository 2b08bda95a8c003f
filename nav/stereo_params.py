"""Parameters of the stereo matcher (census, window, checks) and the default disparity range.

The defaults were tuned on the Middlebury Motorcycle pair that ships with scikit-image
(benchmarks/stereo_accuracy.py, docs/navigation.md): an 8-point sparse census (ring of radius 2)
is as good as the full 5×5 one at a third of the matching work, and a 9×9 box window is where
bad-2 stops improving. The cost-share check costs Motorcycle about a point of bad-2 and removes
the chance matches of textureless regions (rendered sky: 16% of its pixels matched without it,
none with it), which would otherwise be obstacles close to the robot. The small-region filter
removes what still passes at 640×480 (chance matches along a wall's top edge against the sky)
for about 0.2 points of bad-2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.errors import UserError

# Census sample points (dy, dx) around the centre pixel: the 8 corners and edge midpoints of
# the 5×5 square.
RING8_R2: tuple[tuple[int, int], ...] = (
    (-2, -2), (-2, 0), (-2, 2), (0, -2), (0, 2), (2, -2), (2, 0), (2, 2),
)  # fmt: skip
DEFAULT_WINDOW_PX = 9
# The best cost must be below (1 − uniqueness) × the best one at another disparity (not ±1).
DEFAULT_UNIQUENESS = 0.05
DEFAULT_LR_TOLERANCE_PX = 1
# The winner's census codes must differ in less than this share of their bits over the window:
# random codes (a textureless sky or ceiling, where the census is sensor noise) differ in half,
# and their best chance match among D disparities in about 40%.
DEFAULT_MAX_COST_SHARE = 0.3
# Small-region (speckle) filter: a disparity needs at least DEFAULT_MIN_SUPPORT of the neighbours
# sampled every DEFAULT_SUPPORT_STEP_PX within DEFAULT_SUPPORT_RADIUS_PX (48 at the defaults) to
# lie within DEFAULT_SUPPORT_TOLERANCE_PX of it. Chance matches where a window straddles an
# untextured region and an edge (a wall's top edge against the sky at 640×480) pass every
# per-pixel check but come in small, ragged patches; a real surface has neighbours at its depth.
DEFAULT_SUPPORT_RADIUS_PX = 6
DEFAULT_SUPPORT_STEP_PX = 2
DEFAULT_MIN_SUPPORT = 8
DEFAULT_SUPPORT_TOLERANCE_PX = 1.0
MIN_DISPARITIES = 2
MAX_DISPARITIES = 512
# The zoo model's range: a fifth of the image width. With the default camera (60° field of view,
# 6 cm baseline) that is every obstacle from 0.26 m on, at any resolution.
ZOO_DISPARITY_SHARE = 5


@dataclass(frozen=True)
class StereoParams:
    """How disparities are matched: D = ``max_disparity`` candidates 0..D−1 (pixels)."""

    max_disparity: int
    census: tuple[tuple[int, int], ...] = RING8_R2
    window_px: int = DEFAULT_WINDOW_PX
    uniqueness: float = DEFAULT_UNIQUENESS
    lr_tolerance_px: int = DEFAULT_LR_TOLERANCE_PX
    max_cost_share: float = DEFAULT_MAX_COST_SHARE
    min_support: int = DEFAULT_MIN_SUPPORT
    support_radius_px: int = DEFAULT_SUPPORT_RADIUS_PX
    support_step_px: int = DEFAULT_SUPPORT_STEP_PX
    support_tolerance_px: float = DEFAULT_SUPPORT_TOLERANCE_PX

    def __post_init__(self) -> None:
        d = self.max_disparity
        if (
            isinstance(d, bool)
            or not isinstance(d, int)
            or not (MIN_DISPARITIES <= d <= MAX_DISPARITIES)
        ):
            raise UserError(
                f"max disparity must be an integer in {MIN_DISPARITIES}..{MAX_DISPARITIES}, "
                f"got {d!r}"
            )
        if self.window_px < 1 or self.window_px % 2 == 0:
            raise UserError(f"aggregation window must be an odd number of pixels: {self.window_px}")
        if not self.census or (0, 0) in self.census:
            raise UserError("census needs at least one sample point other than the centre")
        if not (math.isfinite(self.uniqueness) and 0 <= self.uniqueness < 1):
            raise UserError(f"uniqueness must be in [0, 1), got {self.uniqueness}")
        if not (math.isfinite(self.max_cost_share) and 0 < self.max_cost_share <= 1):
            raise UserError(f"max cost share must be in (0, 1], got {self.max_cost_share}")
        if self.support_radius_px < 1 or self.support_step_px < 1:
            raise UserError(
                f"support radius and step must be ≥ 1 px, got {self.support_radius_px} and "
                f"{self.support_step_px}"
            )
        if not (0 <= self.min_support <= len(self.support_offsets)):
            raise UserError(
                f"min support must be in 0..{len(self.support_offsets)} (the neighbours "
                f"sampled), got {self.min_support}"
            )
        if not (math.isfinite(self.support_tolerance_px) and self.support_tolerance_px >= 0):
            raise UserError(f"support tolerance must be ≥ 0 px, got {self.support_tolerance_px}")
        if self.lr_tolerance_px < 0:
            raise UserError(f"left-right tolerance must be ≥ 0 px, got {self.lr_tolerance_px}")

    @property
    def census_radius(self) -> int:
        return max(max(abs(dy), abs(dx)) for dy, dx in self.census)

    @property
    def support_offsets(self) -> tuple[tuple[int, int], ...]:
        """The neighbours (dy, dx) the small-region filter samples: a grid every
        ``support_step_px`` within ``support_radius_px``, the centre left out."""
        r, step = self.support_radius_px, self.support_step_px
        grid = range(-(r // step) * step, r + 1, step)
        return tuple((dy, dx) for dy in grid for dx in grid if (dy, dx) != (0, 0))

    def check_image(self, height: int, width: int) -> None:
        """UserError unless an H×W pair can be matched over this disparity range."""
        if self.max_disparity > width:
            raise UserError(
                f"max disparity {self.max_disparity} is more than the image width ({width} px)"
            )
        if min(height, width) < self.window_px:
            raise UserError(
                f"image {width}x{height} is smaller than the {self.window_px}-pixel window"
            )


def zoo_disparities(width: int) -> int:
    """The zoo model's disparity range for an image width (a multiple of 8)."""
    return max(MIN_DISPARITIES, 8 * round(width / ZOO_DISPARITY_SHARE / 8))
