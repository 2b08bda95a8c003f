"""Verification: every cut's prefix then suffix against the full model, on seeded random input.

The reference is the full model run by onnxruntime on its own (weights read from the file). The
runtime that serves the cuts, with its weights shared between sessions, is given by the caller
(a :data:`RunnerFactory`): it must first agree with the reference on the full model, then every
cut is compared with it, then every segment (prefix, segment, suffix of its end). This module
does not know that runtime, only the calls it answers.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import onnxruntime as ort

from common.errors import UserError
from common.partition.errors import CutError, ort_reason
from common.partition.manifest import Partition, TensorSpec

# Verification tolerance: absolute, for float32 outputs; float16 gets a looser one.
FLOAT32_ATOL = 1e-5
FLOAT16_ATOL = 1e-3
VERIFY_SEED = 0


class CutRunner(Protocol):
    """What verification asks of the runtime that serves a split (``SplitModel`` answers it)."""

    def run_full(self, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]: ...

    def run_prefix(self, k: int, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]: ...

    def run_suffix(self, k: int, tensors: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]: ...

    def run_segment(
        self, start: int, end: int, tensors: Mapping[str, np.ndarray]
    ) -> dict[str, np.ndarray]: ...

    def release(self, k: int) -> None: ...


RunnerFactory = Callable[[Partition, int | None], CutRunner]
"""Builds the runtime for a split written to disk, with this many intra-op threads (None: all)."""


@dataclass
class CutCheck:
    """How one cut compared with the full model: its largest error, and why it fails ("" if not)."""

    max_abs_err: float | None = None
    failure: str = ""


def sample_feeds(specs: Sequence[TensorSpec], seed: int = VERIFY_SEED) -> dict[str, np.ndarray]:
    """Seeded random input for each spec: standard normal floats, small integers, random bools."""
    rng = np.random.default_rng(seed)
    feeds: dict[str, np.ndarray] = {}
    for spec in specs:
        dtype = np.dtype(spec.dtype)
        if dtype.kind == "f":
            value = rng.standard_normal(spec.shape).astype(dtype)
        elif dtype.kind in "iu":
            value = rng.integers(0, 10, size=spec.shape).astype(dtype)
        elif dtype.kind == "b":
            value = rng.integers(0, 2, size=spec.shape).astype(bool)
        else:
            raise UserError(f"input {spec.name!r} has unsupported dtype {dtype}")
        feeds[spec.name] = value
    return feeds


def verify_cuts(
    part: Partition,
    feeds: Mapping[str, np.ndarray],
    runner: RunnerFactory,
    *,
    atol: float,
    threads: int | None,
) -> list[CutCheck]:
    """Run prefix then suffix for every cut of ``part`` and compare with the full model.

    UserError if the shared-weight runtime does not reproduce onnxruntime's own run of the full
    model (nothing it computes could be trusted); otherwise one check per cut, in order.
    """
    reference = _reference(part, feeds, threads)
    runtime = runner(part, threads)
    try:
        _, failure = compare(reference, runtime.run_full(feeds), atol)
    except Exception as exc:
        failure = ort_reason(exc)
    if failure:
        # A graph optimization rewrote a shared initializer in place (see common.partition.sharing):
        # every session holding that node would compute with it in its old layout.
        raise UserError(
            f"onnxruntime runs {part.model} on its own, but not with its weights shared "
            f"between sessions: {failure}"
        )
    return [_check_cut(part, k, runtime, feeds, reference, atol) for k in range(len(part.cuts))]


def verify_segments(
    part: Partition,
    feeds: Mapping[str, np.ndarray],
    runner: RunnerFactory,
    *,
    atol: float,
    threads: int | None,
) -> list[CutCheck]:
    """Run prefix, segment, then the suffix of the segment's end for every segment of ``part``
    and compare with the full model; one check per segment, in order. The cuts themselves were
    verified first (``verify_cuts``), so a failure here is the segment's."""
    reference = _reference(part, feeds, threads)
    runtime = runner(part, threads)
    checks: list[CutCheck] = []
    for seg in part.segments:
        check = CutCheck()
        try:
            sent = runtime.run_prefix(seg.start, feeds)
            middle = runtime.run_segment(seg.start, seg.end, sent)
            for expected in part.cut_specs(seg.end):
                got = middle[expected.name]
                if tuple(got.shape) != expected.shape:
                    raise CutError(f"segment output {expected.name!r} has shape {got.shape}")
            # No original feeds here either: the robot's tail runs from the reply alone.
            result = runtime.run_suffix(seg.end, middle)
            check.max_abs_err, failure = compare(reference, result, atol)
            if failure:
                check.failure = f"verification failed: {failure}"
        except CutError as exc:
            check.failure = f"verification failed: {exc}"
        except Exception as exc:
            check.failure = f"onnxruntime failed on this segment: {ort_reason(exc)}"
        checks.append(check)
    return checks


def _reference(
    part: Partition, feeds: Mapping[str, np.ndarray], threads: int | None
) -> dict[str, np.ndarray]:
    """The full model's outputs, run by onnxruntime on its own (weights read from the file)."""
    try:
        session = _own_weights_session(part.full, threads)
        names = [o.name for o in session.get_outputs()]
        return dict(zip(names, session.run(names, dict(feeds)), strict=True))
    except Exception as exc:
        raise UserError(f"onnxruntime cannot run {part.model}: {ort_reason(exc)}") from None


def _check_cut(
    part: Partition,
    k: int,
    runtime: CutRunner,
    feeds: Mapping[str, np.ndarray],
    reference: Mapping[str, np.ndarray],
    atol: float,
) -> CutCheck:
    check = CutCheck()
    try:
        sent = runtime.run_prefix(k, feeds)
        for expected in part.cut_specs(k):
            got = sent[expected.name]
            if tuple(got.shape) != expected.shape:
                raise CutError(f"prefix output {expected.name!r} has shape {got.shape}")
        # No original feeds here: the suffix must run from the cut tensors alone.
        result = runtime.run_suffix(k, sent)
        check.max_abs_err, failure = compare(reference, result, atol)
        if failure:
            check.failure = f"verification failed: {failure}"
    except CutError as exc:
        check.failure = f"verification failed: {exc}"
    except Exception as exc:
        check.failure = f"onnxruntime failed on this cut: {ort_reason(exc)}"
    finally:
        runtime.release(k)
    return check


def compare(
    reference: Mapping[str, np.ndarray], result: Mapping[str, np.ndarray], atol: float
) -> tuple[float, str]:
    """Largest absolute difference over all outputs, and why it is too large ("" if it is not)."""
    worst = 0.0
    for name, ref in reference.items():
        got = result.get(name)
        if got is None:
            return float("inf"), f"output {name!r} is missing"
        if got.shape != ref.shape or got.dtype != ref.dtype:
            return float("inf"), f"output {name!r} is {got.dtype}{list(got.shape)}"
        if ref.dtype.kind in "fc":
            ref_nan, got_nan = np.isnan(ref), np.isnan(got)
            if not np.array_equal(ref_nan, got_nan):
                return float("inf"), f"output {name!r} has NaN where the full model has none"
            diff = np.abs(ref.astype(np.float64) - got.astype(np.float64))[~ref_nan]
        else:
            diff = np.abs(ref.astype(np.float64) - got.astype(np.float64))
        err = float(diff.max()) if diff.size else 0.0
        worst = max(worst, err)
        bound = _tolerance(ref.dtype, atol)
        if not err <= bound:
            return worst, f"output {name!r} differs by {err:.3g} (tolerance {bound:g})"
    return worst, ""


def _tolerance(dtype: np.dtype, atol: float) -> float:
    if dtype == np.float16:
        return max(atol, FLOAT16_ATOL)
    if dtype.kind in "fc":
        return atol
    return 0.0


def _own_weights_session(path: Path, threads: int | None) -> ort.InferenceSession:
    """A plain session of ``path``, weights read from the file (not shared), with the split
    runtime's default level and no pre-packing: the same kernels, hence the same numbers."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    opts.add_session_config_entry("session.disable_prepacking", "1")
    opts.log_severity_level = 3
    if threads:
        opts.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
