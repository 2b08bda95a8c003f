"""Fuzzing the simulator's file loaders (`robotd.sim.trace`): `load_trace` (YAML) and `load_profile`
(the partitioner's profile JSON). Whatever the text, the result is a valid trace or profile (every
number finite, at least one segment or cut) or a UserError on one line, within a time and memory
bound.

Inputs: arbitrary text; the shipped traces and profiles with slices replaced by the format's
tokens or random text; and the inputs known to escape the YAML and JSON parsers as something other
than their own error.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from common.errors import UserError
from robotd.policies.base import CutTable
from robotd.sim.trace import Trace, load_profile, load_trace
from tests.unit.fuzz_support import (
    JSON_FRAGMENTS,
    YAML_FRAGMENTS,
    budget,
    edit_text,
    run_decoder,
    text_edits,
)

ROOT = Path(__file__).resolve().parents[2]
TRACES = [
    p.read_text(encoding="utf-8") for p in sorted((ROOT / "deploy" / "traces").glob("*.yaml"))
]
PROFILES = [
    p.read_text(encoding="utf-8")
    for p in sorted((ROOT / "tests" / "data" / "profiles").glob("*.json"))
]
ESCAPES_YAML = {
    "deep nesting (RecursionError)": "segments: " + "[" * 1000,
    "a 13th month (ValueError)": "frames_per_second: 2001-13-45\n",
    "!!bool of text (KeyError)": "frames_per_second: !!bool maybe\n",
    "a 5000-digit integer (ValueError)": "frames_per_second: 1" + "0" * 5000 + "\n",
    "infinity": "frames_per_second: .inf\nsegments: [{frames: 1, uplink_mbit: 1, downlink_mbit: 1, "
    "rtt_ms: 0, robot_cpu: 1, cloud_speedup: 1}]\n",
}
ESCAPES_JSON = {
    "deep nesting (RecursionError)": "[" * 100_000,
    "a 5000-digit integer (ValueError)": '{"full_ms": 1' + "0" * 5000 + "}",
    "Infinity": '{"full_ms": Infinity, "cuts": [{"index": 0, "bytes": 1, "prefix_ms": 0, '
    '"suffix_ms": 1}]}',
    "1e400": '{"full_ms": 1e400, "cuts": [{"index": 0, "bytes": 1, "prefix_ms": 0, '
    '"suffix_ms": 1}]}',
}


@pytest.fixture(scope="module")
def folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="fuzz-trace-") as name:
        yield Path(name)


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    return path


def trace_or_error(folder: Path, text: str) -> Trace | None:
    path = _write(folder, "trace.yaml", text)
    loaded = run_decoder(lambda: load_trace(path), (UserError,), max_bytes=256 * len(text) + 1)
    if loaded is None:
        return None
    trace, _ = loaded
    assert isinstance(trace, Trace) and trace.total_frames >= 1
    numbers = [trace.frames_per_second, trace.noise.jitter, trace.deadline_ms or 1.0]
    for segment in trace.segments:
        numbers += [segment.uplink_mbit, segment.downlink_mbit, segment.rtt_ms]
        numbers += [segment.robot_cpu, segment.cloud_speedup]
    assert all(math.isfinite(x) for x in numbers), numbers
    return trace


def profile_or_error(folder: Path, text: str) -> CutTable | None:
    path = _write(folder, "profile.json", text)
    loaded = run_decoder(lambda: load_profile(path), (UserError,), max_bytes=256 * len(text) + 1)
    if loaded is None:
        return None
    table, _ = loaded
    assert isinstance(table, CutTable) and table.size >= 1
    for column in (table.bytes, table.prefix_s, table.suffix_s, table.cloud_s):
        assert np.isfinite(column).all() and (column >= 0).all(), column
    assert math.isfinite(table.full_s) and table.full_s > 0
    return table


@budget(100)
@given(text=st.text(max_size=200))
def test_trace_arbitrary_text(folder: Path, text: str) -> None:
    trace_or_error(folder, text)


@budget(150)
@given(base=st.sampled_from(TRACES), edits=text_edits(YAML_FRAGMENTS))
def test_traces_edited(folder: Path, base: str, edits: list[tuple[int, int, str]]) -> None:
    trace_or_error(folder, edit_text(base, edits))


@budget(100)
@given(text=st.text(max_size=200))
def test_profile_arbitrary_text(folder: Path, text: str) -> None:
    profile_or_error(folder, text)


@budget(150)
@given(base=st.sampled_from(PROFILES), edits=text_edits(JSON_FRAGMENTS))
def test_profiles_edited(folder: Path, base: str, edits: list[tuple[int, int, str]]) -> None:
    profile_or_error(folder, edit_text(base, edits))


@pytest.mark.parametrize("text", list(ESCAPES_YAML.values()), ids=list(ESCAPES_YAML))
def test_trace_inputs_that_escaped_the_loader(folder: Path, text: str) -> None:
    path = _write(folder, "trace.yaml", text)
    with pytest.raises(UserError, match="trace "):
        run_decoder(lambda: load_trace(path), ())


@pytest.mark.parametrize("text", list(ESCAPES_JSON.values()), ids=list(ESCAPES_JSON))
def test_profile_inputs_that_escaped_the_loader(folder: Path, text: str) -> None:
    path = _write(folder, "profile.json", text)
    with pytest.raises(UserError, match="profile "):
        run_decoder(lambda: load_profile(path), ())


def test_the_shipped_files_still_load(folder: Path) -> None:
    """The edits start from files that load (else only the error paths would be tested)."""
    assert all(trace_or_error(folder, text) is not None for text in TRACES)
    assert all(profile_or_error(folder, text) is not None for text in PROFILES)
