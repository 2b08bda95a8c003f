"""Fuzzing the split model's loaders: `Partition.load` (a split directory's manifest.json, read by
every daemon at start) and the profiler's cache reader (`common.profiler`, whose broken entries
are measured again). Whatever the text, `Partition.load` gives a partition whose every tensor
spec has a size (a known dtype, sizes >= 0) and whose cuts are numbered, or a UserError on one
line; the cache reader gives a profile of the contract's form or None. Both within a time and
memory bound.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common import profiler
from common.errors import UserError
from common.partition import MANIFEST_FORMAT, MANIFEST_NAME, Partition
from tests.unit.fuzz_support import JSON_FRAGMENTS, budget, edit_text, run_decoder, text_edits

MANIFEST: dict[str, Any] = {
    "format": MANIFEST_FORMAT,
    "model": "tiny",
    "digest": "9f" * 32,
    "inputs": ["x"],
    "outputs": ["y"],
    "cuts": [
        {
            "index": 0,
            "tensors": ["x"],
            "bytes": 48,
            "prefix": None,
            "suffix": "cut000.suffix.onnx",
            "verified": True,
            "max_abs_err": 0.0,
            "prefix_flops": 0,
            "suffix_flops": 120,
        },
        {
            "index": 1,
            "tensors": ["h"],
            "bytes": 32,
            "prefix": "cut001.prefix.onnx",
            "suffix": "cut001.suffix.onnx",
            "verified": True,
            "max_abs_err": 1.5e-7,
            "prefix_flops": 60,
            "suffix_flops": 60,
        },
    ],
    "excluded": [{"tensors": ["a", "b"], "reason": "more than 1 tensor"}],
    "specs": {
        "x": {"dtype": "float32", "shape": [1, 3, 2, 2]},
        "h": {"dtype": "float16", "shape": [1, 4, 2, 2]},
        "y": {"dtype": "int64", "shape": [1]},
    },
    "full": "full.onnx",
    "weights": "weights.bin",
    "options": {"cuts": "auto", "max_cut_tensors": 1},
}
PROFILE: dict[str, Any] = {
    "digest": "9f" * 32,
    "full_ms": 1.25,
    "cuts": [
        {
            "index": 0,
            "tensors": ["x"],
            "bytes": 48,
            "prefix_ms": 0.0,
            "suffix_ms": 1.2,
            "prefix_flops": 0,
            "suffix_flops": 120,
        }
    ],
}
TEXTS = [json.dumps(MANIFEST, indent=1), json.dumps(MANIFEST)]
PROFILE_TEXTS = [json.dumps(PROFILE, indent=1)]
ESCAPES = {
    "a list (AttributeError)": "[]",
    "a cut that is a list (AttributeError)": json.dumps({**MANIFEST, "cuts": [[1]]}),
    "a size of 1e400 (OverflowError)": json.dumps(MANIFEST).replace("[1, 3, 2, 2]", "[1e400]"),
    "deep nesting (RecursionError)": "[" * 100_000,
    "a negative size": json.dumps(MANIFEST).replace("[1, 3, 2, 2]", "[1, -3, 2, 2]"),
    "a dtype numpy does not know": json.dumps(MANIFEST).replace('"float16"', '"float17"'),
    "not UTF-8": b"\xff\xfe{".decode("latin-1"),
}


@pytest.fixture(scope="module")
def folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="fuzz-manifest-") as name:
        yield Path(name)


def manifest_or_error(folder: Path, text: str) -> Partition | None:
    (folder / MANIFEST_NAME).write_bytes(text.encode("utf-8", errors="surrogatepass"))
    part = run_decoder(lambda: Partition.load(folder), (UserError,), max_bytes=256 * len(text) + 1)
    if part is not None:
        assert isinstance(part, Partition)
        for spec in part.specs.values():
            assert spec.nbytes >= 0 and all(isinstance(d, int) for d in spec.shape)
        assert all(isinstance(c.index, int) and isinstance(c.bytes, int) for c in part.cuts)
    return part


def cached_profile(folder: Path, text: str) -> dict[str, Any] | None:
    path = folder / "profile.json"
    path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    profile = run_decoder(lambda: profiler._read(path), (), max_bytes=256 * len(text) + 1)
    if profile is not None:
        assert isinstance(profile["digest"], str)
        assert math.isfinite(profile["full_ms"]) and profile["full_ms"] >= 0
        for cut in profile["cuts"]:
            assert isinstance(cut["index"], int) and isinstance(cut["bytes"], int)
            assert math.isfinite(cut["prefix_ms"]) and math.isfinite(cut["suffix_ms"])
    return profile


@budget(100)
@given(text=st.text(max_size=200))
def test_manifest_arbitrary_text(folder: Path, text: str) -> None:
    manifest_or_error(folder, text)


@budget(150)
@given(base=st.sampled_from(TEXTS), edits=text_edits(JSON_FRAGMENTS))
def test_manifests_edited(folder: Path, base: str, edits: list[tuple[int, int, str]]) -> None:
    manifest_or_error(folder, edit_text(base, edits))


@budget(100)
@given(base=st.sampled_from(PROFILE_TEXTS), edits=text_edits(JSON_FRAGMENTS))
def test_cached_profiles_edited(folder: Path, base: str, edits: list[tuple[int, int, str]]) -> None:
    cached_profile(folder, edit_text(base, edits))


@pytest.mark.parametrize("text", list(ESCAPES.values()), ids=list(ESCAPES))
def test_manifests_that_escaped_the_loader(folder: Path, text: str) -> None:
    (folder / MANIFEST_NAME).write_bytes(text.encode("latin-1", errors="replace"))
    with pytest.raises(UserError, match="manifest"):
        run_decoder(lambda: Partition.load(folder), ())


@pytest.mark.parametrize(
    "text",
    [
        "[" * 100_000,
        json.dumps({**PROFILE, "full_ms": "fast"}),
        json.dumps({**PROFILE, "cuts": [{"index": 0}]}),
        json.dumps(PROFILE).replace("1.25", "NaN"),
        json.dumps(PROFILE).replace('"bytes": 48', '"bytes": true'),
    ],
    ids=["deep-nesting", "full_ms-text", "cut-without-fields", "nan", "bool-bytes"],
)
def test_broken_cache_entries_are_measured_again(folder: Path, text: str) -> None:
    """A corrupt profile in the cache reads as no entry (the profiler measures again), never
    as a profile a policy would get, nor as a RecursionError."""
    assert cached_profile(folder, text) is None


def test_the_examples_still_load(folder: Path) -> None:
    part = manifest_or_error(folder, TEXTS[0])
    assert part is not None and [c.index for c in part.cuts] == [0, 1]
    assert cached_profile(folder, PROFILE_TEXTS[0]) == PROFILE
