"""d_coll(K) geometry against hand-computed arcs: straight ahead, left and right turns, points
beside and behind the axle, R → ∞; the bins of a wall; the interpolated profile; the bins
within the robot's half width of a path."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.errors import UserError
from nav.curvature import (
    CurvatureBins,
    DcollProfile,
    ObstacleBand,
    arc_to_point,
    dcoll_from_points,
)
from tests.helpers.nav import OFFCENTRE_640_FRAME34

coords = st.floats(-5.0, 5.0, allow_nan=False).filter(lambda v: abs(v) > 1e-3)


def test_straight_ahead() -> None:
    k, s = arc_to_point(np.array([0.0]), np.array([2.0]))
    assert k[0] == 0.0 and s[0] == 2.0


def test_left_and_right_quarter_turns() -> None:
    # (∓1, 1) lies a quarter of the way round the unit circle centred at (∓1, 0).
    k, s = arc_to_point(np.array([-1.0, 1.0]), np.array([1.0, 1.0]))
    assert k.tolist() == [1.0, -1.0]  # left turn: K > 0 (ω > 0)
    np.testing.assert_allclose(s, [math.pi / 2, math.pi / 2])


def test_points_beside_and_behind_the_axle() -> None:
    # beside: half a circle of radius 0.25; behind-right: three quarters of the unit circle;
    # straight behind: never reached driving forward.
    k, s = arc_to_point(np.array([0.5, 1.0, 0.0]), np.array([0.0, -1.0, -1.0]))
    np.testing.assert_allclose(k, [-4.0, -1.0, 0.0])
    np.testing.assert_allclose(s[:2], [math.pi * 0.25, 1.5 * math.pi])
    assert s[2] == math.inf


def test_radius_to_infinity_tends_to_y() -> None:
    k, s = arc_to_point(np.array([1e-9, -1e-7, 1e-4]), np.array([2.0, 3.0, 1.0]))
    np.testing.assert_allclose(s, [2.0, 3.0, 1.0], rtol=1e-7)
    assert np.all(np.abs(k) < 3e-4)


def test_origin_has_no_arc() -> None:
    k, s = arc_to_point(np.array([0.0]), np.array([0.0]))
    assert np.isnan(k[0]) and np.isnan(s[0])


@given(coords, coords)
def test_matches_the_papers_formula_mirrored(x: float, y: float) -> None:
    """The paper's s = R·(π − atan2(y, x − x_c)) for a point on the right; mirror for the left."""
    k, s = arc_to_point(np.array([x]), np.array([y]))
    xr = abs(x)
    x_c = (xr * xr + y * y) / (2 * xr)
    paper = x_c * (math.pi - math.atan2(y, xr - x_c))
    assert s[0] == pytest.approx(paper, rel=1e-9, abs=1e-9)
    assert k[0] == pytest.approx(-math.copysign(1.0, x) / x_c)
    # the point is on the circle of that curvature, and no arc is shorter than its chord
    centre = -1.0 / k[0]
    assert (x - centre) ** 2 + y * y == pytest.approx(centre * centre, rel=1e-9)
    assert s[0] >= math.hypot(x, y) * (1 - 1e-12)


def wall(y: float, x_from: float, x_to: float, height: float = 0.3) -> np.ndarray:
    xs = np.linspace(x_from, x_to, 20001)
    return np.stack([xs, np.full_like(xs, y), np.full_like(xs, height)], axis=-1)


def test_a_wall_ahead_fills_the_bins_it_crosses() -> None:
    bins, band = CurvatureBins(2.0, 41), ObstacleBand(max_range_m=5.0)
    d = dcoll_from_points(wall(2.0, -1.0, 1.0), bins, band)
    centres = bins.centres()
    assert d[centres.tolist().index(0.0)] == pytest.approx(2.0)
    # wall points have K = −2x/(x² + 4), |K| ≤ 0.4 for |x| ≤ 1: the bin of K = 0.2 holds
    # K in [0.15, 0.25); its nearest point is at K = 0.15: x = −0.3035, s = 2.0305 m.
    i = int(np.argmin(np.abs(centres - 0.2)))
    assert d[i] == pytest.approx(2.0305, abs=1e-3)
    assert d[i] == pytest.approx(d[len(d) - 1 - i])  # symmetric wall, symmetric profile
    assert np.all(d[np.abs(centres) > 0.45] == band.max_range_m)
    assert np.all(np.diff(d[centres >= 0]) >= 0)  # tighter turns reach the wall later


def test_floor_and_overhead_points_are_not_obstacles() -> None:
    points = np.concatenate([wall(1.0, -1, 1, height=0.01), wall(1.5, -1, 1, height=2.0)])
    assert np.all(dcoll_from_points(points) == ObstacleBand().max_range_m)


def test_nan_points_are_skipped_and_arcs_capped() -> None:
    points = np.array([[np.nan, 1.0, 0.3], [0.0, 9.0, 0.3], [0.0, 1.0, np.nan]])
    d = dcoll_from_points(points, band=ObstacleBand(max_range_m=4.0))
    assert np.all(d == 4.0)


def test_profile_interpolates_and_clamps() -> None:
    profile = DcollProfile(np.array([-1.0, 0.0, 1.0]), np.array([3.0, 1.0, 2.0]))
    assert profile.at(0.0) == 1.0
    assert profile.at(0.5) == pytest.approx(1.5)
    assert profile.at(-0.25) == pytest.approx(1.5)
    assert profile.at(7.0) == 2.0 and profile.at(-7.0) == 3.0


def test_profile_from_bins_checks_the_count() -> None:
    bins = CurvatureBins(1.0, 5)
    assert DcollProfile.from_bins(bins, np.arange(5.0)).at(0.5) == 3.0
    with pytest.raises(UserError, match="4 values for 5 curvature bins"):
        DcollProfile.from_bins(bins, np.arange(4.0))


def test_within_sees_the_face_beside_an_empty_path_bin() -> None:
    profile = DcollProfile.from_bins(CurvatureBins(), np.array(OFFCENTRE_640_FRAME34))
    assert profile.at(0.0) == 5.0  # the axle's path alone: nothing ahead
    assert profile.within(0.0, 0.0) == 5.0
    # Within 0.2 m of the path: the nearest of the bins around it, K = 0.4 at 0.40 m among them
    # (0.4·0.40²/2 = 3 cm to the left).
    assert profile.within(0.0, 0.2) == pytest.approx(math.sin(0.4 * 0.40) / 0.4, abs=1e-9)


def test_within_ignores_what_is_farther_from_the_path_than_the_half_width() -> None:
    # One obstacle, in the bin K = −1 at 1 m: (1 − cos 1, sin 1) = (0.460, 0.841) m.
    profile = DcollProfile(np.array([-1.0, 0.0, 1.0]), np.array([1.0, 5.0, 5.0]))
    assert profile.within(0.0, 0.45) == 5.0
    assert profile.within(0.0, 0.47) == pytest.approx(math.sin(1.0))
    # On a right turn of radius 2 it is 2 − |(0.460, 0.841) − (2, 0)| = 0.245 m inside, at the
    # angle atan2(0.841, 1.540) of the circle from the axle.
    inside = 2.0 - math.hypot(2.0 - (1 - math.cos(1.0)), math.sin(1.0))
    assert inside == pytest.approx(0.2448, abs=1e-4)
    assert profile.within(-0.5, inside + 1e-6) == pytest.approx(
        2.0 * math.atan2(math.sin(1.0), 2.0 - (1 - math.cos(1.0)))
    )
    assert profile.within(-0.5, inside - 1e-6) == profile.at(-0.5) == 3.0  # interpolated
    # The mirror image on the left.
    mirrored = DcollProfile(np.array([-1.0, 0.0, 1.0]), np.array([5.0, 5.0, 1.0]))
    assert mirrored.within(0.5, inside + 1e-6) == profile.within(-0.5, inside + 1e-6)


@given(
    st.floats(-2.0, 2.0),
    st.floats(0.05, 3.0),  # less than a full turn at |K| ≤ 2, as any arc of arc_to_point
    st.floats(-2.0, 2.0),
    st.floats(0.0, 1.0),
)
def test_within_is_never_more_than_the_path_bins_own(
    bin_k: float, distance: float, path_k: float, half_width: float
) -> None:
    seen = DcollProfile(np.array([bin_k - 0.1, bin_k, bin_k + 0.1]), np.array([5.0, distance, 5.0]))
    assert seen.within(path_k, half_width) <= seen.at(path_k)
    assert seen.within(path_k, 0.0) == seen.at(path_k)
    # on the bin's own path the obstacle is on the path, at its own arc
    assert seen.within(bin_k, half_width) == pytest.approx(distance)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: CurvatureBins(2.0, 40), "odd"),
        (lambda: CurvatureBins(-1.0, 41), "positive curvature"),
        (lambda: ObstacleBand(0.5, 0.4), "below max height"),
        (lambda: ObstacleBand(max_range_m=0.0), "max range"),
        (lambda: DcollProfile(np.zeros(3), np.ones(3)).within(0.0, -0.1), "half width"),
    ],
)
def test_bad_settings_are_named(make: object, message: str) -> None:
    with pytest.raises(UserError, match=message):
        make()  # type: ignore[operator]
