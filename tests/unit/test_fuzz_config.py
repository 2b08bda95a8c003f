"""Fuzzing the fleet config loader (`common.config.load_fleet`): whatever the text of fleet.yaml,
the result is a FleetConfig or a UserError on one line (the CLI prints it and exits 2), within a
time and memory bound.

Inputs: arbitrary text; the valid example files (tests/config_cases/valid-*.yaml) with slices
replaced by YAML tokens or random text; the valid files parsed, one value replaced by any
YAML-able value, and dumped again (this reaches the model's validators); and the YAML inputs
known to escape PyYAML as something other than a YAMLError.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from common.config import FleetConfig, load_fleet
from common.errors import UserError
from tests.unit.fuzz_support import YAML_FRAGMENTS, budget, edit_text, run_decoder, text_edits

CASES = Path(__file__).resolve().parents[1] / "config_cases"
VALID_TEXTS = [p.read_text(encoding="utf-8") for p in sorted(CASES.glob("valid-*.yaml"))]
# Each was a crash (not a UserError) before the loader caught what PyYAML and pathlib raise.
ESCAPES = {
    # PyYAML's scanner is quadratic in the flow nesting depth: the recursion limit, reached at a
    # few hundred levels, is what bounds it (about 2 s whatever the depth, 0.3 s at 1000).
    "deep nesting (RecursionError)": "service: " + "[" * 1000,
    "a 13th month (ValueError)": "service: vision\ncreated: 2001-13-45\n",
    "!!timestamp of text (AttributeError)": "service: !!timestamp vision\n",
    "!!bool of text (KeyError)": "service: !!bool maybe\n",
    "!!int of text (ValueError)": "deadline_s: !!int x\n",
    "a list as a key (TypeError)": "? [a, b]\n: c\n",
    "a map as a key (TypeError)": "? {a: 1}\n: c\n",
    "a 5000-digit integer (ValueError)": "max_payload_bytes: 1" + "0" * 5000 + "\n",
    "~user of no such user (RuntimeError)": (
        "service: vision\nmodel: ~nosuchuser/m.onnx\nlatency_bound: {seconds: 0.3}\n"
        "deadline_s: 0.5\n"
    ),
    "a recursive alias": "service: vision\npolicy: {kind: elastic, params: &a {x: *a}}\n",
    "an alias bomb": "".join(
        f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]\n" if i else "l0: &l0 [lol]\n"
        for i in range(9)
    )
    + "service: *l8\n",
}


@pytest.fixture(scope="module")
def folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="fuzz-config-") as name:
        yield Path(name)


def load(folder: Path, text: str) -> FleetConfig | None:
    """load_fleet on `text` as a file; a FleetConfig, or None after a one-line UserError."""
    path = folder / "fleet.yaml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    config = run_decoder(
        lambda: load_fleet(path), (UserError,), max_bytes=256 * len(text.encode(errors="replace"))
    )
    assert config is None or isinstance(config, FleetConfig)
    return config


@budget(100)
@given(text=st.text(max_size=300))
def test_arbitrary_text(folder: Path, text: str) -> None:
    load(folder, text)


@budget(150)
@given(base=st.sampled_from(VALID_TEXTS), edits=text_edits(YAML_FRAGMENTS))
def test_valid_files_edited(folder: Path, base: str, edits: list[tuple[int, int, str]]) -> None:
    load(folder, edit_text(base, edits))


yaml_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats()
    | st.text(max_size=12)
    | st.sampled_from(["zoo:vgg", "tls/0.0.0.0:7447", "robot", "cloud", "service", "p95"]),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3)
    ),
    max_leaves=10,
)


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every path to a value inside parsed YAML (maps by key, lists by index)."""
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            out += _paths(item, (*prefix, index))
    return out


def _replaced(tree: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(tree, dict):
        return {**tree, head: _replaced(tree[head], rest, value)}
    return [_replaced(item, rest, value) if i == head else item for i, item in enumerate(tree)]


@budget(80)
@given(data=st.data(), base=st.sampled_from(VALID_TEXTS), value=yaml_values)
def test_one_value_replaced(folder: Path, data: st.DataObject, base: str, value: Any) -> None:
    tree = yaml.safe_load(base)
    path = data.draw(st.sampled_from(_paths(tree)))
    load(folder, yaml.safe_dump(_replaced(tree, path, value), allow_unicode=True))


@pytest.mark.parametrize("text", list(ESCAPES.values()), ids=list(ESCAPES))
def test_yaml_that_escapes_pyyaml_is_a_user_error(folder: Path, text: str) -> None:
    # No memory bound here: tracemalloc makes the deep-nesting case 30x slower.
    with pytest.raises(UserError, match=r"invalid YAML|fleet\.yaml: "):
        run_decoder(lambda: load_fleet(_write(folder, text)), ())


def _write(folder: Path, text: str) -> Path:
    path = folder / "fleet.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_the_valid_examples_still_load(folder: Path) -> None:
    """The edits above start from files that load: a broken example would leave only the
    error paths tested."""
    for text in VALID_TEXTS:
        assert isinstance(load(folder, text), FleetConfig)
