"""`bench nav --table5 live`'s pieces that need no testbed: the option's check, the robot's
`--source` for a maneuver (read back by the source itself, `--t-dead` included), and Table V's
figures from the maneuvers' outcome lines."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from common.errors import UserError
from common.source_spec import SourceError
from experiments.nav_live import figures, maneuver_spec
from experiments.nav_rows import TABLE5_LIVE, TABLE5_SIM, parse_table5
from nav.maneuver_source import StereoManeuverSource
from nav.shared_control import DEFAULT_DEADLINE_S
from robotd.sources.opening import open_source


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
    assert spec == f"stereo:maneuver:3:lap=2:assist=off:t_dead=1.0:out={out}"
    source = open_source(spec, height=48, width=64)
    try:
        assert isinstance(source, StereoManeuverSource)
        assert (source.index, source.lap, source.out) == (3, 2, out)
        assert not source.drive.drive.assisted
        assert source.drive.drive.control.params.deadline_s == DEFAULT_DEADLINE_S
    finally:
        source.close()


def test_the_benchs_t_dead_reaches_the_robots_assistant(tmp_path: Path) -> None:
    """`--t-dead` crosses to the robot daemon in its `--source`; a value that does not read
    back as the same float would drive the live Table V at another T_dead than the sim's."""
    spec = maneuver_spec(0, 0, True, tmp_path / "o.json", 2.7)
    assert ":t_dead=2.7:" in spec
    source = open_source(spec, height=48, width=64)
    try:
        assert isinstance(source, StereoManeuverSource)
        assert source.drive.drive.control.params.deadline_s == 2.7
        assert "T_dead 2.7 s" in source.description
    finally:
        source.close()


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "soon"])
def test_a_bad_t_dead_in_the_source_is_one_line(value: str) -> None:
    with pytest.raises(SourceError, match=f"t_dead='{value}' is not a positive number"):
        open_source(f"stereo:maneuver:0:t_dead={value}", height=48, width=64)


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
