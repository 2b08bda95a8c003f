"""The demo's script loader (deploy/demo_script.py): the packaged default and good files resolve
to phases with their first frame and inherited settings; bad files are one-line errors naming the
file and the field; what the robot is handed (`--phases`) reads back as the same phases."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.errors import UserError
from deploy.demo import DemoOptions
from deploy.demo_script import DEFAULT_SCRIPT, default_script, load_script, single_phase
from robotd.emulation import Phase, load_phases


def write(tmp_path: Path, text: str, name: str = "script.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_the_packaged_default_script_loads_and_kills_in_its_last_phase() -> None:
    assert DEFAULT_SCRIPT.is_file()
    script = default_script()
    assert len(script.phases) >= 3
    assert script.kill_at == script.phases[-1].first
    # The default shows both sides: a link where offloading pays and one where it does not.
    rates = [p.uplink_mbit for p in script.phases]
    assert all(r is not None for r in rates)
    assert max(r for r in rates if r is not None) >= 10 * min(r for r in rates if r is not None)
    assert all(p.slowdown > 1 for p in script.phases)
    assert script.frames == sum(p.frames for p in script.phases)


def test_phases_inherit_settings_and_get_their_first_frame(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
description: inherit
slowdown: 2
uplink_mbit: 8
fps: 12
phases:
  - {name: a, frames: 10}
  - {name: b, frames: 5, uplink_mbit: 0.5, slowdown: 6}
  - {name: c, frames: 7}
  - {name: d, frames: 3, uplink_mbit: null, kill_service: true}
""",
    )
    script = load_script(path)
    assert script.phases == (
        Phase("a", 0, 10, 8.0, 2.0),
        Phase("b", 10, 5, 0.5, 6.0),
        Phase("c", 15, 7, 0.5, 6.0),
        Phase("d", 22, 3, None, 6.0),
    )
    assert script.kill_at == 22
    assert script.fps == 12
    assert script.description == "inherit"
    assert script.frames == 25


def test_the_robot_reads_back_the_phases_it_is_handed(tmp_path: Path) -> None:
    script = load_script(
        write(
            tmp_path,
            "slowdown: 3\nphases:\n  - {name: x, frames: 4, uplink_mbit: 2}\n"
            "  - {name: y, frames: 6, uplink_mbit: null}\n",
        )
    )
    robot_file = write(tmp_path, script.robot_phases_yaml(), "phases.yaml")
    assert tuple(load_phases(robot_file)) == script.phases


def test_overrides_set_every_phase_and_move_the_kill(tmp_path: Path) -> None:
    script = load_script(
        write(
            tmp_path,
            "phases:\n  - {name: a, frames: 4, uplink_mbit: 2, slowdown: 2}\n"
            "  - {name: b, frames: 4, uplink_mbit: 9, kill_service: true}\n",
        )
    )
    changed = script.with_overrides(uplink_mbit=1.5, slowdown=5, kill_at=1)
    assert [p.uplink_mbit for p in changed.phases] == [1.5, 1.5]
    assert [p.slowdown for p in changed.phases] == [5, 5]
    assert changed.kill_at == 1
    assert script.with_overrides().phases == script.phases


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("phases: [}", "invalid YAML"),
        ("- a\n- b\n", "expected a mapping with a list of phases"),
        ("phases: []", "phases: List should have at least 1 item"),
        ("description: no phases\n", "phases: required key is missing"),
        ("phases:\n  - {name: a}\n", "phases[0].frames: required key is missing"),
        ("phases:\n  - {name: a, frames: 0}\n", "phases[0].frames: Input should be greater"),
        (
            "phases:\n  - {name: a, frames: 3, uplink_mbit: -1}\n",
            "phases[0].uplink_mbit: Input should be greater than 0",
        ),
        (
            "phases:\n  - {name: a, frames: 3, uplink_mbit: .inf}\n",
            "phases[0].uplink_mbit: Input should be a finite number",
        ),
        (
            "phases:\n  - {name: a, frames: 3, slowdown: 0.5}\n",
            "phases[0].slowdown: Input should be greater than or equal to 1",
        ),
        (
            "phases:\n  - {name: a, frames: 3, uplnk_mbit: 2}\n",
            "phases[0].uplnk_mbit: unknown key; did you mean 'uplink_mbit'?",
        ),
        ("phases:\n  - {name: a, frames: 3}\nspeed: 2\n", "speed: unknown key"),
        (
            "phases:\n  - {name: a, frames: 3,\n     frames: 4}\n",
            "line 3, column 6: duplicate key 'frames', first given on line 2",
        ),
        (
            "phases:\n  - {name: a, frames: 3}\n  - {name: a, frames: 3}\n",
            "phases[1].name 'a' is used by an earlier phase",
        ),
        (
            "phases:\n  - {name: a, frames: 3, kill_service: true}\n"
            "  - {name: b, frames: 3, kill_service: true}\n",
            "phases[1].kill_service: only one phase may kill",
        ),
        ("fps: 0\nphases:\n  - {name: a, frames: 3}\n", "fps: Input should be greater than 0"),
    ],
)
def test_bad_scripts_are_one_line_errors_naming_file_and_field(
    tmp_path: Path, text: str, expected: str
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(UserError) as caught:
        load_script(path)
    message = str(caught.value)
    assert message.startswith(f"--script {path}: "), message
    assert expected in message, message
    assert "\n" not in message


def test_a_missing_script_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"--script .*nowhere\.yaml: no such file"):
        load_script(tmp_path / "nowhere.yaml")


def test_single_phase_runs_frames_without_a_script() -> None:
    script = single_phase(40, uplink_mbit=2.0, slowdown=3.0, kill_at=None)
    assert script.phases == (Phase("run", 0, 40, 2.0, 3.0),)
    with pytest.raises(UserError, match="--frames 0"):
        single_phase(0, uplink_mbit=None, slowdown=1.0, kill_at=None)


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        (DemoOptions(frames=10, kill_service_at=10), r"--kill-service-at 10: .* 0\.\.9"),
        (DemoOptions(uplink_mbit=0), "--uplink-mbit 0"),
        (DemoOptions(robot_slowdown=0.5), "--robot-slowdown 0.5"),
        (DemoOptions(fps=-1), "--fps -1"),
        (DemoOptions(policy="fastest"), "--policy fastest"),
        (DemoOptions(frames=5, script=DEFAULT_SCRIPT), "--script and --frames"),
    ],
)
def test_bad_demo_options_are_refused_before_anything_starts(
    options: DemoOptions, expected: str
) -> None:
    with pytest.raises(UserError, match=expected):
        options.resolve()


def test_demo_options_without_script_take_the_default_and_override_it() -> None:
    default = default_script()
    assert DemoOptions().resolve() == default
    faster = DemoOptions(robot_slowdown=1.0, fps=30).resolve()
    assert {p.slowdown for p in faster.phases} == {1.0}
    assert faster.fps == 30
    one = DemoOptions(frames=40, kill_service_at=15).resolve()
    assert [p.frames for p in one.phases] == [40]
    assert one.kill_at == 15
    assert one.phases[0].slowdown == default.phases[0].slowdown
