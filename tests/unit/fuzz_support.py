"""What every fuzz test of a decoder checks, and the budget the fuzz tests run in.

The property, for every decoder (wire messages, tensor codecs, fleet config, trace, profile and
split manifest loaders): whatever the input, the decoder returns a valid object or raises the
project's named error for bad input (`WireError`, `UserError`), with a message on one line, and
it does so within a time and a memory bound. Another exception, a hang or an allocation out of
proportion to the input fails the test. `run_decoder` checks one input that way.

Budget: `budget(n)` gives hypothesis settings of n examples, scaled by ELASTICFOG_FUZZ_SCALE
(default 1: every `test_fuzz_*.py` together in well under a minute on two cores; e.g. 50 for a
long run by hand). The per-example deadline only flags slow examples; the watchdog of
`run_decoder` is what turns a decoder that never returns into a failure.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import resource
import signal
import tracemalloc
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

T = TypeVar("T")

FUZZ_SCALE_ENV = "ELASTICFOG_FUZZ_SCALE"
# Generous against a loaded CI host, and still thousands of times what one decode takes.
EXAMPLE_DEADLINE_S = 2.0
# A decoder still running after this long is taken for a hang (the inputs are a few KiB).
HANG_AFTER_S = 10.0
# Interpreter and library noise on top of what an input may legitimately cost (lazy imports,
# caches, a first OpenCV or msgpack call).
MEMORY_SLACK_BYTES = 4 * 1024 * 1024
# Native libraries (OpenCV, libjpeg-turbo) allocate outside tracemalloc's view: their share is
# bounded by the process's peak resident size, which grows on a lazy import too, hence the slack.
RSS_SLACK_BYTES = 256 * 1024 * 1024


def budget(examples: int, *, deadline_s: float = EXAMPLE_DEADLINE_S) -> settings:
    """Hypothesis settings for one fuzz test: `examples` examples (scaled, see the module
    docstring) and a per-example deadline."""
    scale = float(os.environ.get(FUZZ_SCALE_ENV, "1"))
    return settings(
        max_examples=max(1, round(examples * scale)),
        deadline=dt.timedelta(seconds=deadline_s),
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.filter_too_much,
        ],
    )


class DecoderHang(AssertionError):
    """A decoder that did not return within HANG_AFTER_S."""


class DecoderMemory(AssertionError):
    """A decoder that allocated more than its input justifies."""


@contextlib.contextmanager
def watchdog(seconds: float = HANG_AFTER_S) -> Iterator[None]:
    """Raise DecoderHang in the main thread if the body runs longer than `seconds` (SIGALRM:
    pytest runs tests on the main thread)."""

    def expired(signum: int, frame: Any) -> None:
        raise DecoderHang(f"the decoder did not return within {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


@contextlib.contextmanager
def memory_bound(max_bytes: int) -> Iterator[None]:
    """Fail with DecoderMemory if the body's peak of traced allocations (Python objects, numpy
    arrays, zstd output) exceeds `max_bytes` plus MEMORY_SLACK_BYTES, or if it raised the
    process's peak resident size by more than that plus RSS_SLACK_BYTES (native allocations)."""
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base, _ = tracemalloc.get_traced_memory()
    rss_before = _peak_rss_bytes()
    try:
        yield
    finally:
        _, peak = tracemalloc.get_traced_memory()
        if started:
            tracemalloc.stop()
    allowed = max_bytes + MEMORY_SLACK_BYTES
    if peak - base > allowed:
        raise DecoderMemory(f"the decoder allocated {peak - base} bytes, allowed {allowed}")
    grown = _peak_rss_bytes() - rss_before
    if grown > allowed + RSS_SLACK_BYTES:
        raise DecoderMemory(
            f"the process's peak resident size grew by {grown} bytes during the decode, allowed "
            f"{allowed + RSS_SLACK_BYTES}"
        )


def run_decoder(
    decode: Callable[[], T],
    errors: tuple[type[Exception], ...],
    *,
    max_bytes: int | None = None,
) -> T | None:
    """`decode()` under the watchdog (and the memory bound when `max_bytes` is given); None when
    it raised one of `errors` with a one-line message. Any other exception propagates."""
    with contextlib.ExitStack() as bounds:
        bounds.enter_context(watchdog())
        if max_bytes is not None:
            bounds.enter_context(memory_bound(max_bytes))
        try:
            return decode()
        except errors as exc:
            message = str(exc)
            assert message, f"{type(exc).__name__} without a message"
            assert "\n" not in message, f"{type(exc).__name__} message spans lines: {message!r}"
            return None


def mutate(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    """`data` with each (position, length, replacement) edit applied in turn: `length` bytes at
    `position` (both taken modulo the current size) replaced by `replacement`; an empty
    replacement deletes, a zero length inserts."""
    out = bytearray(data)
    for position, length, replacement in edits:
        at = position % (len(out) + 1)
        out[at : at + length] = replacement
    return bytes(out)


byte_edits = st.lists(
    st.tuples(
        st.integers(min_value=0, max_value=2**20),
        st.integers(min_value=0, max_value=8),
        st.binary(max_size=8) | st.sampled_from([b"\x00", b"\xff", b"\x7f", b"\x80"]),
    ),
    min_size=1,
    max_size=6,
)
"""Edits for `mutate`: a few overwrites, insertions and deletions."""


def text_edits(fragments: list[str]) -> st.SearchStrategy[list[tuple[int, int, str]]]:
    """Edits of a text: a few slices replaced by arbitrary text or by one of `fragments` (the
    tokens of the format, where random text rarely lands)."""
    return st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=2**16),
            st.integers(min_value=0, max_value=12),
            st.sampled_from(fragments) | st.text(max_size=8),
        ),
        min_size=1,
        max_size=5,
    )


def edit_text(text: str, edits: list[tuple[int, int, str]]) -> str:
    """`text` with (position, length, replacement) edits applied, as `mutate` does for bytes."""
    for position, length, replacement in edits:
        at = position % (len(text) + 1)
        text = text[:at] + replacement + text[at + length :]
    return text


# YAML tokens random text rarely produces: anchors and aliases, tags, flow and block markers,
# scalars PyYAML resolves to other types (timestamps, floats, booleans, null), odd keys.
YAML_FRAGMENTS = [
    "\n",
    ": ",
    "- ",
    "? ",
    "[",
    "]",
    "{",
    "}",
    ", ",
    "&a ",
    "*a",
    "<<: *a",
    "!!binary ",
    "!!timestamp ",
    "!!bool ",
    "!!int ",
    "!!float ",
    "!!set ",
    "!!omap ",
    "!!python/object:os.system ",
    "2001-13-45",
    "2001-12-14t21:59:43.10-05:00",
    ".inf",
    "-.nan",
    "0x1F",
    "0o17",
    "1_000",
    "~",
    "null",
    "yes",
    '"\\0"',
    '"\\x00"',
    "~nosuchuser/model.onnx",
    '"a\\nb": ',
    '"\\t": ',
    "zoo:",
    "tls/",
    "tcp/127.0.0.1:99999",
    "\t",
    "#",
    "|\n  ",
    "%YAML 1.1\n---\n",
    "...\n",
    "\ufeff",
]
# JSON tokens random text rarely produces: Python's json accepts NaN and Infinity, 1e400 overflows
# to inf, a 5000-digit integer is refused by int(), a lone surrogate decodes.
JSON_FRAGMENTS = [
    "{",
    "}",
    "[",
    "]",
    ",",
    ": ",
    '"',
    "null",
    "true",
    "-1",
    "0",
    "0.5",
    "NaN",
    "Infinity",
    "-Infinity",
    "1e400",
    "1" + "0" * 5000,
    '"\\ud800"',
    '"\\u0000"',
    '"index": ',
    '"codecs": []',
    '"codecs": [{"name": "jpeg80", "bytes": 1}]',
    "[" * 50,
]
