"""Distance to collision per curvature, s = d_coll(K) (the paper's Section III-C), in numpy.

Every obstacle point (x, y) on the floor (frame of :mod:`nav.camera`: x right, y forward, origin
at the axle centre) lies on exactly one circle through the origin tangent to the heading, centre
(x_c, 0) with x_c = (x² + y²)/2x and R = |x_c|: driving along it the robot hits the point after
the arc length s. The paper writes s = R·(π − atan2(y, x − x_c)) for a point on the right
(x > 0, centre on the right) and s = y as R → ∞; mirrored for x < 0. Here s is evaluated as
2R·β with β = atan2(|x|, y), the angle between the heading and the chord (the tangent–chord angle
is half the arc's central angle): the same value, and no cancellation as R → ∞, where it tends to
y. A point behind the axle (y < 0) is reached after more than half a turn; straight behind
(x = 0, y ≤ 0) never.

Signs: the paper's K = 1/R is unsigned; the assistant needs the side, so K here is signed as the
joystick's K_j = ω_j/v_j (REP 103: ω > 0 turns left). A point on the right (x > 0) lies on a right
turn: K = −2x/(x² + y²) = −1/x_c.

d_coll(K) is kept per curvature bin (bin centres evenly spaced over [−K_max, K_max]): the nearest
obstacle whose curvature rounds to the bin, ``max_range_m`` where none does, and linear
interpolation between bin centres (clamped at the outer bins: a frontal camera sees no sharper
turns). :func:`dcoll_from_points` is the reference of the ONNX ``d_coll`` stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.errors import UserError

DEFAULT_K_MAX_PER_M = 2.0
DEFAULT_BIN_COUNT = 41
# Points lower than this are the floor, higher than the robot pass over it (metres).
DEFAULT_MIN_HEIGHT_M = 0.05
DEFAULT_MAX_HEIGHT_M = 0.60
# d_coll of a bin with no obstacle, and the cap of every arc length.
DEFAULT_MAX_RANGE_M = 5.0
# A path curvature below this (1/m) is straight for DcollProfile.within: 1 µm off over 1 km.
_STRAIGHT_PER_M = 1e-9


@dataclass(frozen=True)
class CurvatureBins:
    """``count`` bin centres evenly spaced over [−k_max, k_max] (1/m); ``count`` is odd, so
    straight ahead (K = 0) is a centre."""

    k_max_per_m: float = DEFAULT_K_MAX_PER_M
    count: int = DEFAULT_BIN_COUNT

    def __post_init__(self) -> None:
        if not (math.isfinite(self.k_max_per_m) and self.k_max_per_m > 0):
            raise UserError(f"k_max must be a positive curvature (1/m), got {self.k_max_per_m}")
        if self.count < 3 or self.count % 2 == 0:
            raise UserError(f"curvature bins: count must be odd and at least 3, got {self.count}")

    @property
    def step_per_m(self) -> float:
        return 2 * self.k_max_per_m / (self.count - 1)

    def centres(self) -> np.ndarray:
        return np.linspace(-self.k_max_per_m, self.k_max_per_m, self.count)

    def index(self, curvature: np.ndarray) -> np.ndarray:
        """Nearest bin of each curvature as a float (rounded half to even, as ONNX Round);
        values outside 0..count−1 (or NaN) fall in no bin."""
        return np.round(
            (np.asarray(curvature, dtype=np.float64) + self.k_max_per_m) / self.step_per_m
        )


@dataclass(frozen=True)
class ObstacleBand:
    """Which points are obstacles: height above the floor within [min, max]; arc lengths are
    capped at ``max_range_m``, which is also d_coll where nothing is seen."""

    min_height_m: float = DEFAULT_MIN_HEIGHT_M
    max_height_m: float = DEFAULT_MAX_HEIGHT_M
    max_range_m: float = DEFAULT_MAX_RANGE_M

    def __post_init__(self) -> None:
        if not self.min_height_m < self.max_height_m:
            raise UserError(
                f"obstacle band: min height {self.min_height_m} m must be below max height "
                f"{self.max_height_m} m"
            )
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise UserError(f"obstacle band: max range must be positive, got {self.max_range_m}")


def arc_to_point(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed curvature K (1/m, > 0 left) and arc length s (m) of the circular path from the axle
    centre, heading +y, through each point (x, y). The origin itself gives NaN for both."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    r2 = x * x + y * y
    ax = np.abs(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        curvature = np.where(r2 > 0, -2.0 * x / r2, np.nan)
        beta = np.arctan2(ax, y)
        arc = np.where(ax > 0, r2 * beta / ax, np.where(y > 0, y, np.inf))
    return curvature, np.where(r2 > 0, arc, np.nan)


def dcoll_from_points(
    points: np.ndarray,
    bins: CurvatureBins | None = None,
    band: ObstacleBand | None = None,
) -> np.ndarray:
    """d_coll per curvature bin (metres, one value per bin centre) from points (…×3: x, y, z in
    the ground frame; rows with NaN are no point)."""
    bins = bins or CurvatureBins()
    band = band or ObstacleBand()
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1] != 3:
        raise UserError(f"points must have 3 coordinates in their last axis, got {pts.shape}")
    pts = pts.reshape(-1, 3)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    with np.errstate(invalid="ignore"):
        obstacle = (z >= band.min_height_m) & (z <= band.max_height_m)
    curvature, arc = arc_to_point(x, y)
    index = bins.index(curvature)
    with np.errstate(invalid="ignore"):
        keep = obstacle & (index >= 0) & (index <= bins.count - 1)
    out = np.full(bins.count, band.max_range_m)
    np.minimum.at(out, index[keep].astype(np.int64), np.minimum(arc[keep], band.max_range_m))
    return out


@dataclass(frozen=True)
class DcollProfile:
    """d_coll(K) from one frame: distances at the bin centres, linearly interpolated."""

    curvatures: np.ndarray
    distances: np.ndarray
    max_range_m: float = DEFAULT_MAX_RANGE_M
    """A bin at this distance or more saw nothing."""

    def __post_init__(self) -> None:
        if self.curvatures.shape != self.distances.shape or self.curvatures.ndim != 1:
            raise UserError(
                f"d_coll profile: {self.curvatures.shape} curvatures for "
                f"{self.distances.shape} distances"
            )

    @classmethod
    def from_bins(cls, bins: CurvatureBins, distances: np.ndarray) -> DcollProfile:
        values = np.asarray(distances, dtype=np.float64).reshape(-1)
        if values.shape != (bins.count,):
            raise UserError(f"d_coll has {values.size} values for {bins.count} curvature bins")
        return cls(bins.centres(), values)

    def at(self, curvature: float) -> float:
        """Distance to collision along the path of this curvature (clamped to the outer bins)."""
        return float(np.interp(curvature, self.curvatures, self.distances))

    def within(self, curvature: float, half_width_m: float) -> float:
        """Distance along the path of this curvature to the first obstacle of any bin that lies
        within ``half_width_m`` of the path (the robot's body, not only its axle centre), and
        never more than :meth:`at`. Each bin's obstacle is placed at its bin centre's curvature
        (off by up to half a bin step: ±0.05·s² m laterally at the defaults, 5 mm at 0.3 m).

        Why: a bin is ΔK·s²/2 wide across the path, so near an obstacle the path's own bin is a
        sliver (±6 mm at 0.5 m) that a few unmatched pixels leave empty, and an empty bin reads
        as free to ``max_range_m``; the bins beside it see the same face.
        """
        if not (math.isfinite(half_width_m) and half_width_m >= 0):
            raise UserError(f"half width must be ≥ 0 m, got {half_width_m}")
        along = self.at(curvature)
        if half_width_m == 0:
            return along
        seen = self.distances < self.max_range_m
        x, y = _on_arc(self.curvatures[seen], self.distances[seen])
        lateral, ahead = _from_path(curvature, x, y)
        near = lateral <= half_width_m
        return float(min(along, ahead[near].min(initial=math.inf)))


def _on_arc(curvature: np.ndarray, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the point reached after ``arc`` metres on the path of signed ``curvature`` from
    the axle centre heading +y: x = −(1 − cos Ks)/K, y = sin(Ks)/K, written with h = Ks/2 as
    x = −s·sinc(h)·sin h, y = s·sinc(h)·cos h so that K → 0 gives (0, s) exactly."""
    half = 0.5 * np.asarray(curvature, dtype=np.float64) * arc
    safe = np.where(half != 0, half, 1.0)
    sinc = np.where(half != 0, np.sin(half) / safe, 1.0)
    return -arc * sinc * np.sin(half), arc * sinc * np.cos(half)


def _from_path(curvature: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of each point (x, y) from the path of signed ``curvature`` (a circle through the
    axle centre, or the +y axis), and the arc length along the path to the point's foot on it
    (inf for a point behind on a straight path). Mirrored to a left turn (centre (−1/k, 0),
    k = |K|): with q = (k·x + 1, k·y), the distance is ||q| − 1|/k = |2x + k·r²|/(|q| + 1),
    which tends to |x| as k → 0, and the foot is at the angle of q, counter-clockwise."""
    side = 1.0 if curvature >= 0 else -1.0
    k = abs(curvature)
    xm = side * np.asarray(x, dtype=np.float64)
    ym = np.asarray(y, dtype=np.float64)
    qx, qy = k * xm + 1.0, k * ym
    norm = np.hypot(qx, qy)
    lateral = np.abs(2.0 * xm + k * (xm * xm + ym * ym)) / (norm + 1.0)
    if k < _STRAIGHT_PER_M:
        return lateral, np.where(ym > 0, ym, np.inf)
    angle = np.mod(np.arctan2(qy, qx), 2 * math.pi)
    return lateral, angle / k
