"""`bench nav --table5 live`'s pieces that need no testbed: the option's check, the robot's
`--source` for a maneuver (read back by the source itself), and Table V's figures from the
maneuvers' outcome lines."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from common.errors import UserError
from deploy.experiments.nav_live import figures, maneuver_spec
from deploy.experiments.nav_rows import TABLE5_LIVE, TABLE5_SIM, parse_table5
from robotd.maneuver_source import StereoManeuverSource
from robotd.sources import open_source


def outcome(collided: bool, clearance: float, distance: float) -> dict[str, Any]:
    return {"collided": collided, "min_clearance_m": clearance, "distance_m": distance}


def test_table5_mode_is_sim_or_live() -> None:
    assert parse_table5("sim") == TABLE5_SIM
    assert parse_table5(" LIVE ") == TABLE5_LIVE
    with pytest.raises(UserError, match="--table5: expected sim or live, got 'real'"):
        parse_table5("real")


def test_the_maneuver_spec_opens_that_maneuver(tmp_path: Path) -> None:
    out = tmp_path / "o.json"
    spec = maneuver_spec(3, 2, False, out)
    assert spec == f"stereo:maneuver:3:lap=2:assist=off:out={out}"
    source = open_source(spec, height=48, width=64)
    try:
        assert isinstance(source, StereoManeuverSource)
        assert (source.index, source.lap, source.out) == (3, 2, out)
        assert not source.drive.drive.assisted
    finally:
        source.close()


def test_an_outcome_path_with_a_colon_is_refused() -> None:
    """The source's spec separates its options with colons."""
    with pytest.raises(UserError, match="must not contain ':'"):
        maneuver_spec(0, 0, True, Path("/tmp/a:b/o.json"))


def test_figures_count_collisions_and_keep_the_clear_runs_smallest_clearance() -> None:
    got = figures(
        [outcome(True, -0.001, 1.0), outcome(False, 0.25, 0.5), outcome(False, 0.21, 1.2)]
    )
    assert (got.collisions, got.maneuvers) == (1, 3)
    assert got.distance_m == pytest.approx(0.9)
    assert got.min_clearance_m == pytest.approx(0.21)
    every_one_hit = figures([outcome(True, -0.002, 1.0)])
    assert every_one_hit.min_clearance_m is None and every_one_hit.collisions == 1
