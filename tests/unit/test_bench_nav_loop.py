"""`bench nav`'s Table V in the in-process loop (`--table5 sim`) at the bench's T_dead: with
every frame's latency past the assistant's default T_dead (1 s) the assisted robot is held at
rest, and a T_dead above the latency lets it drive. Guards against `--t-dead` not reaching the
loop, which would leave Table V at 640x480 (latencies of 1.1-2.3 s) with a robot that never
moves. Simulated time at the smallest resolution, one latency: deterministic, under a second."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from common.errors import UserError
from experiments.nav import RESULT_FILE, keep_result
from experiments.nav_loop import LoopResult, table5
from experiments.nav_rows import OFF

SIZE = (64, 48)
LABEL = "64x48"
LATENCY_S = 1.5
"""Above the assistant's default T_dead, below the raised one: as at 640x480 on this host."""


def drive(deadline_s: float) -> LoopResult:
    return table5([SIZE], [1, OFF], {(1, LABEL): [LATENCY_S]}, 1, deadline_s=deadline_s)


def first_maneuver(loop: LoopResult) -> dict[str, object]:
    outcome = loop.maneuvers[(1, LABEL)][0]
    assert (outcome["lap"], outcome["maneuver_index"]) == (0, 0)
    return outcome


def test_latency_past_the_default_t_dead_holds_the_robot_at_rest() -> None:
    loop = drive(1.0)
    assert first_maneuver(loop)["distance_m"] == 0.0
    assert loop.figures[(1, LABEL)].distance_m == 0.0
    assert loop.figures[(1, LABEL)].collisions == 0  # says nothing: it never moved


def test_a_t_dead_above_the_latency_lets_the_assisted_robot_drive() -> None:
    loop = drive(3.0)
    outcome = first_maneuver(loop)
    assert outcome["distance_m"] > 0.5
    assert outcome["frames"] >= 2  # one frame in flight at a time, each 1.5 s
    assert len(loop.maneuvers[(1, LABEL)]) == 7  # one lap of the circuit
    # T_dead plays no part without the assistant: every unassisted maneuver collides.
    assert loop.figures[(OFF, LABEL)].collisions == 7
    assert all(m["collided"] for m in loop.maneuvers[(OFF, LABEL)])


def test_the_whole_result_is_kept_in_the_workdir(tmp_path: Path) -> None:
    """The JSON contract prints the rows only; the settings (T_dead among them) and the
    per-maneuver details are kept beside the run's logs."""
    result = {
        "settings": {"t_dead_s": 3.0},
        "results": [{"option": 1}],
        "details": [{"option": 1, "maneuvers": [{"distance_m": 1.2}]}],
        "plots": {"dcoll": [1.0] * 1000},
    }
    path = keep_result(result, tmp_path / "w")
    assert path == tmp_path / "w" / RESULT_FILE
    kept = json.loads(path.read_text(encoding="utf-8"))
    assert kept == {key: result[key] for key in ("settings", "results", "details")}


@pytest.mark.parametrize("deadline_s", [0.0, -1.0])
def test_the_loop_refuses_a_t_dead_that_is_not_positive(deadline_s: float) -> None:
    with pytest.raises(UserError, match="deadline_s must be a positive number"):
        drive(deadline_s)
