"""Profiling a split model on this host: bytes, prefix/suffix time and FLOPs per cut.

The result is the profile contract of ``elasticfog model profile --json``::

    {digest, full_ms, cuts: [{index, tensors, bytes, prefix_ms, suffix_ms,
                              prefix_flops, suffix_flops}]}

Times are medians over ``runs`` timed runs after warm-up, with the same sessions (shared weights)
the daemons use. A profile describes this host, so it is cached in the user cache directory,
keyed by the model digest and everything that changes the figures (cut options, input shape,
runs, threads); a second call returns the cached profile without running anything.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from common.errors import UserError
from common.models import cache_dir, read_cached_json, write_cached_json
from common.partition import (
    DEFAULT_MAX_CUT_TENSORS,
    InputShape,
    load_partition,
    sample_feeds,
)

DEFAULT_RUNS = 20
WARMUP_RUNS = 2
MAX_RUNS = 10_000
PROFILE_FORMAT = 1


def profile_model(
    spec: str | Path,
    runs: int = DEFAULT_RUNS,
    threads: int | None = None,
    input_shape: InputShape = None,
    progress: bool = False,
    *,
    cuts: str | Sequence[str] = "auto",
    max_cut_tensors: int = DEFAULT_MAX_CUT_TENSORS,
    refresh: bool = False,
) -> dict[str, Any]:
    """Profile every cut of a model on this host (or return the cached profile).

    ``threads`` sets onnxruntime's intra-op threads (None: its default, all cores). With
    ``progress`` a progress bar is drawn on stderr. ``refresh`` ignores the cache.
    """
    if not isinstance(runs, int) or not 1 <= runs <= MAX_RUNS:
        raise UserError(f"--runs must be 1..{MAX_RUNS}, got {runs!r}")
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise UserError(f"--threads must be a positive integer, got {threads!r}")
    part = load_partition(spec, cuts, max_cut_tensors, input_shape)
    key = _cache_key(part.digest, part.options, runs, threads)
    path = cache_dir() / "profiles" / f"{part.digest[:16]}-{key}.json"
    if not refresh:
        cached = _read(path)
        if cached is not None:
            return cached
    result = _measure(part, runs, threads, progress)
    write_cached_json(path, result)
    return result


def _measure(part: Any, runs: int, threads: int | None, progress: bool) -> dict[str, Any]:
    from common.partition.runtime import SplitModel

    runtime = SplitModel(part, threads=threads, lazy=True)
    feeds = sample_feeds(runtime.input_specs())
    steps = 1 + len(part.cuts)
    with _progress_bar(progress, f"profiling {part.model}", steps) as advance:
        full_ms = median_ms(lambda: runtime.run_full(feeds), runs)
        advance()
        rows = []
        for k, cut in enumerate(part.cuts):
            sent = runtime.run_prefix(k, feeds)
            prefix_ms = 0.0
            if cut.prefix is not None:
                prefix_ms = median_ms(functools.partial(runtime.run_prefix, k, feeds), runs)
            suffix_ms = median_ms(functools.partial(runtime.run_suffix, k, sent), runs)
            # One cut's sessions at a time keeps profiling memory flat in the number of cuts.
            runtime.release(k)
            rows.append(
                {
                    "index": cut.index,
                    "tensors": list(cut.tensors),
                    "bytes": cut.bytes,
                    "prefix_ms": round(prefix_ms, 4),
                    "suffix_ms": round(suffix_ms, 4),
                    "prefix_flops": cut.prefix_flops,
                    "suffix_flops": cut.suffix_flops,
                }
            )
            advance()
    return {"digest": part.digest, "full_ms": round(full_ms, 4), "cuts": rows}


def median_ms(fn: Callable[[], object], runs: int) -> float:
    """Median wall time of ``fn`` in milliseconds over ``runs`` calls, after a short warm-up."""
    for _ in range(WARMUP_RUNS):
        fn()
    times = np.empty(runs)
    for i in range(runs):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1000.0)


class _progress_bar:
    """A rich progress bar on stderr (so ``--json`` output stays clean), or nothing."""

    def __init__(self, enabled: bool, label: str, total: int) -> None:
        self.enabled = enabled
        self.label = label
        self.total = total
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> Callable[[], None]:
        if not self.enabled:
            return lambda: None
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

        self._progress = Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self._progress.start()
        self._task = self._progress.add_task(self.label, total=self.total)
        return lambda: self._progress.advance(self._task)

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.stop()


def _cache_key(digest: str, options: dict[str, Any], runs: int, threads: int | None) -> str:
    src = json.dumps(
        {
            "format": PROFILE_FORMAT,
            "digest": digest,
            "options": options,
            "runs": runs,
            "threads": threads,
            "onnxruntime": ort.__version__,
        },
        sort_keys=True,
    )
    return hashlib.sha256(src.encode()).hexdigest()[:16]


def _read(path: Path) -> dict[str, Any] | None:
    """The cached profile at `path`, or None when there is none or it is not of the contract's
    form (a broken entry is measured again, and never reaches a policy)."""
    try:
        data = read_cached_json(path)
    except RecursionError:  # JSON nested thousands deep (tests/unit/test_fuzz_partition.py)
        return None
    return data if _is_profile(data) else None


def _is_profile(data: Any) -> bool:
    """A digest, a finite `full_ms` and cuts each with an integer index and byte count and
    finite times: what the policies read."""
    if not isinstance(data, dict) or not isinstance(data.get("digest"), str):
        return False
    cuts = data.get("cuts")
    if not _non_negative(data.get("full_ms"), float) or not isinstance(cuts, list):
        return False
    return all(
        isinstance(cut, dict)
        and _non_negative(cut.get("index"), int)
        and _non_negative(cut.get("bytes"), int)
        and _non_negative(cut.get("prefix_ms"), float)
        and _non_negative(cut.get("suffix_ms"), float)
        for cut in cuts
    )


def _non_negative(value: Any, kind: type) -> bool:
    """A finite number >= 0 (an int where `kind` is int; booleans are not numbers here)."""
    if isinstance(value, bool) or not isinstance(value, int if kind is int else (int, float)):
        return False
    return math.isfinite(value) and value >= 0
