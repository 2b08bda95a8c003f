"""The navigation assistant as a safety filter on Twists: the operator's forward speed limited by
the newest d_coll on the same path, the other components passed, a stale or missing d_coll a
ramp to a stop, bad d_coll refused by name."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.errors import UserError
from common.ros2_messages import Twist
from nav.assist import TeleopAssist
from nav.shared_control import PAPER_A_MAX_MPS2, AssistantParams, Limit

BINS = 31
T0 = 1_700_000_000.0


def _at(t_s: float) -> int:
    return round(t_s * 1e9)


def test_no_d_coll_yet_no_forward_motion() -> None:
    safe = TeleopAssist().command(Twist((0.3, 0.0, 0.0), (0.0, 0.0, 0.2)), now_s=T0)
    assert safe.limit is Limit.DEADLINE
    assert safe.twist.linear[0] == 0.0 and safe.twist.angular[2] == 0.0


def test_free_path_passes_unchanged() -> None:
    assist = TeleopAssist()
    assert assist.observe(np.full(BINS, 10.0, np.float32), _at(T0))
    twist = Twist((0.3, 0.01, 0.0), (0.0, 0.02, 0.1))
    safe = assist.command(twist, now_s=T0 + 0.05)
    assert safe.limit is Limit.NONE and safe.twist == twist


def test_obstacle_slows_on_the_same_path() -> None:
    assist = TeleopAssist()
    assist.observe(np.full(BINS, 0.005, np.float32), _at(T0))
    safe = assist.command(Twist((0.4, 0.0, 0.0), (0.0, 0.0, 0.2)), now_s=T0)
    v_allowed = math.sqrt(2 * PAPER_A_MAX_MPS2 * 0.005)
    assert safe.limit is Limit.OBSTACLE
    assert safe.twist.linear[0] == pytest.approx(v_allowed)
    assert safe.twist.angular[2] / safe.twist.linear[0] == pytest.approx(0.2 / 0.4)


def test_stale_d_coll_ramps_down_to_a_stop() -> None:
    assist = TeleopAssist(AssistantParams(deadline_s=1.0, deadline_decel_mps2=1.0))
    assist.observe(np.full(BINS, 10.0, np.float32), _at(T0))
    assert assist.command(Twist((0.4, 0, 0), (0, 0, 0)), now_s=T0 + 0.5).twist.linear[0] == 0.4
    speeds = [
        assist.command(Twist((0.4, 0, 0), (0, 0, 0)), now_s=T0 + t).twist.linear[0]
        for t in (1.1, 1.2, 1.4, 2.0)
    ]
    assert speeds == pytest.approx([0.3, 0.2, 0.0, 0.0])


def test_reverse_passes_and_older_frames_are_ignored() -> None:
    assist = TeleopAssist()
    assert assist.observe(np.full(BINS, 0.0, np.float32), _at(T0))
    assert not assist.observe(np.full(BINS, 10.0, np.float32), _at(T0 - 1))
    back = Twist((-0.2, 0, 0), (0, 0, 0.3))
    assert assist.command(back, now_s=T0).twist == back
    assert assist.command(Twist((0.2, 0, 0), (0, 0, 0)), now_s=T0).twist.linear[0] == 0.0


@pytest.mark.parametrize("values", [np.zeros(0), np.zeros(2), np.zeros(30)])
def test_d_coll_not_one_value_per_bin_is_refused(values: np.ndarray) -> None:
    with pytest.raises(UserError, match="d_coll"):
        TeleopAssist().observe(values, _at(T0))


def test_bins_from_zoo_stereo_metadata() -> None:
    from nav.assist import bins_of_model
    from nav.zoo_entry import build_stereo

    props = {p.key: p.value for p in build_stereo((3, 120, 160)).metadata_props}
    bins = bins_of_model(props)
    assert bins is not None and bins.count == int(props["nav.bins.count"])
    assert bins_of_model({}) is None
    assist = TeleopAssist(bins=bins)
    with pytest.raises(UserError, match="curvature bins"):
        assist.observe(np.zeros(bins.count + 2), _at(T0))
    assert assist.observe(np.full(bins.count, 5.0), _at(T0))
