"""Which (cut, codec) pairs are actions: bytes, encode/decode time and fidelity, measured.

A codec's worth depends on what crosses: a JPEG of a camera image is 1/50 of its raw float32,
the same codec on a feature map makes no sense, and a lossy codec is only an action if the
model's answer survives it. So each candidate codec of each cut is run on calibration frames
(real frames from the robot's source, so JPEG sizes are those of its camera) and measured:

- bytes on the wire (median and the 10th/90th percentiles: they follow the content),
- encode time (the robot's cost) and decode time (the cloud's), medians,
- fidelity against the uncompressed model: top-1 agreement of every classifier-shaped output
  (N×C with C ≥ 2) and the largest relative L2 error of any output over the frames.

`Fidelity` (fleet.yaml `fidelity:`, `--fidelity` on the CLI) decides which lossy codecs are
actions; lossless codecs always are, when they save at least `MIN_SAVING_SHARE` of the raw
bytes. By default only images may cross lossy (JPEG at the lowest quality of the ladder whose
answers meet the bound): a feature map crosses lossy only with `lossy_features: true`.
A codec a baseline asks for by name (`cloud:jpeg80`) is measured and kept whatever the bound.

The result is one list per cut of the profile's `codecs` entries
(`{name, bytes, bytes_p10, bytes_p90, encode_ms, decode_ms, top1_agreement, rel_err, lossy}`),
raw first; `robotd.policies.CutTable` turns every entry into an action.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from common.errors import UserError
from common.partition import TensorSpec
from common.wire import WireError
from common.wire.tensor_codecs import CODEC_RAW, decode_encoded, encode_tensor_as, parse_codec

if TYPE_CHECKING:
    from common.config import FidelityConfig
    from common.partition.runtime import SplitModel

# JPEG qualities tried on image crossings, best first; the lowest that meets the bound is kept.
JPEG_LADDER = (95, 90, 80, 70, 50)
LOSSLESS_CODECS = ("raw+zstd", "png")
LOSSY_FEATURE_CODECS = ("fp16", "int8", "int8+zstd")
# A lossless codec that saves less than this share of the raw bytes is not worth its CPU time.
MIN_SAVING_SHARE = 0.1
# Offloading actions per cut, raw included: keeps the decision cost flat (16 cuts × 4 codecs).
MAX_CODECS_PER_CUT = 4
MS_PER_S = 1000.0

Feeds = dict[str, np.ndarray]


@dataclass(frozen=True)
class Fidelity:
    """How close to the uncompressed model a lossy codec must keep the answers.

    `min_top1_agreement` applies to classifier-shaped outputs, `max_output_rel_err` (None: not
    checked) to every output; a model with no classifier output needs `max_output_rel_err` for
    any lossy codec. `lossy_features` lets non-image tensors cross lossy (fp16, int8)."""

    def allows(self, name: str) -> bool:
        """True when the codec list (if any) lets `name` be tried."""
        return name == CODEC_RAW or self.codecs is None or name in self.codecs

    min_top1_agreement: float = 0.98
    max_output_rel_err: float | None = None
    lossy_features: bool = False
    codecs: tuple[str, ...] | None = None
    """Only these codecs (and raw) are tried; None: every codec that applies."""

    def admits(self, top1: float | None, rel_err: float) -> bool:
        """True when measured answers meet the bound (a bound that cannot be checked fails)."""
        if top1 is None and self.max_output_rel_err is None:
            return False
        if top1 is not None and top1 < self.min_top1_agreement:
            return False
        return self.max_output_rel_err is None or rel_err <= self.max_output_rel_err


def fidelity_of(config: FidelityConfig) -> Fidelity:
    """The codec profiler's bound from the fleet file's `fidelity:` section; UserError for a
    codec name that does not exist."""
    for name in config.codecs or ():
        try:
            parse_codec(name)
        except WireError as exc:
            raise UserError(f"fidelity.codecs: {exc.reason}") from None
    return Fidelity(
        min_top1_agreement=config.min_top1_agreement,
        max_output_rel_err=config.max_output_rel_err,
        lossy_features=config.lossy_features,
        codecs=tuple(config.codecs) if config.codecs is not None else None,
    )


def is_image(spec: TensorSpec) -> bool:
    """A uint8 tensor an image codec can take (H×W×C with C ∈ {1, 3}, batch of 1 allowed)."""
    return spec.dtype == "uint8" and parse_codec("png").applies_to(
        np.dtype(spec.dtype), tuple(spec.shape)
    )


def candidate_codecs(specs: Sequence[TensorSpec], fidelity: Fidelity) -> list[str]:
    """The codecs worth measuring for a cut carrying `specs` (raw first). A codec must apply to
    every tensor of the cut: the cut's tensors cross together in one codec."""
    if all(is_image(s) for s in specs):
        names = [CODEC_RAW, *LOSSLESS_CODECS, *(f"jpeg{q}" for q in JPEG_LADDER)]
    else:
        names = [CODEC_RAW, "raw+zstd"]
        if fidelity.lossy_features:
            names += LOSSY_FEATURE_CODECS
    if fidelity.codecs is not None:
        names += [n for n in fidelity.codecs if n not in names]
    return [n for n in names if fidelity.allows(n) and _applies(n, specs)]


def _applies(name: str, specs: Sequence[TensorSpec]) -> bool:
    codec = parse_codec(name)
    return all(codec.applies_to(np.dtype(s.dtype), tuple(s.shape)) for s in specs)


@dataclass
class _Measured:
    name: str
    lossy: bool
    bytes: list[int]
    encode_s: list[float]
    decode_s: list[float]
    agree: list[bool]
    rel_err: list[float]

    def entry(self) -> dict[str, Any]:
        sizes = np.asarray(self.bytes, dtype=np.float64)
        return {
            "name": self.name,
            "bytes": float(np.median(sizes)),
            "bytes_p10": float(np.percentile(sizes, 10)),
            "bytes_p90": float(np.percentile(sizes, 90)),
            "encode_ms": round(float(np.median(self.encode_s)) * MS_PER_S, 4),
            "decode_ms": round(float(np.median(self.decode_s)) * MS_PER_S, 4),
            "top1_agreement": float(np.mean(self.agree)) if self.agree else None,
            "rel_err": float(max(self.rel_err)) if self.rel_err else 0.0,
            "lossy": self.lossy,
        }


def measure_codecs(
    specs: Sequence[TensorSpec],
    crossings: Sequence[Mapping[str, np.ndarray]],
    references: Sequence[Mapping[str, np.ndarray]],
    suffix: Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]],
    names: Iterable[str],
) -> list[dict[str, Any]]:
    """Every codec in `names` on one cut: `crossings[i]` are the cut's tensors of calibration
    frame i, `references[i]` the uncompressed model's outputs for it, `suffix` runs the rest of
    the model. Returns one profile entry per codec (see the module docstring)."""
    out = []
    for name in names:
        codec = parse_codec(name)
        m = _Measured(name, codec.lossy, [], [], [], [], [])
        for tensors, reference in zip(crossings, references, strict=True):
            t0 = time.perf_counter()
            encoded = {s.name: encode_tensor_as(tensors[s.name], name) for s in specs}
            t1 = time.perf_counter()
            decoded = {
                s.name: decode_encoded(encoded[s.name], max_bytes=s.nbytes, name=s.name)
                for s in specs
            }
            t2 = time.perf_counter()
            m.bytes.append(sum(e.nbytes for e in encoded.values()))
            m.encode_s.append(t1 - t0)
            m.decode_s.append(t2 - t1)
            if codec.lossy:
                outputs = suffix(decoded)
                agree, err = compare_outputs(outputs, reference)
                if agree is not None:
                    m.agree.append(agree)
                m.rel_err.append(err)
        out.append(m.entry())
    return out


def compare_outputs(
    outputs: Mapping[str, np.ndarray], reference: Mapping[str, np.ndarray]
) -> tuple[bool | None, float]:
    """(top-1 agreement of every classifier-shaped output, or None if there is none; the largest
    relative L2 error of any output)."""
    agree: bool | None = None
    worst = 0.0
    for name, ref in reference.items():
        got = np.asarray(outputs[name], dtype=np.float64)
        want = np.asarray(ref, dtype=np.float64)
        norm = float(np.linalg.norm(want))
        diff = float(np.linalg.norm(got - want))
        worst = max(worst, diff / norm if norm > 0 else diff)
        if want.ndim == 2 and want.shape[1] >= 2:
            same = bool(np.array_equal(got.argmax(axis=1), want.argmax(axis=1)))
            agree = same if agree is None else agree and same
    return agree, worst


def select_codecs(
    entries: Sequence[Mapping[str, Any]], fidelity: Fidelity, required: Iterable[str] = ()
) -> list[dict[str, Any]]:
    """The entries that are actions: raw; lossless codecs that save bytes; for JPEG the lowest
    quality that meets the bound; other lossy codecs that meet it; and whatever `required`
    names (a baseline asks for it). At most MAX_CODECS_PER_CUT, raw and required first, then
    by bytes."""
    must = set(required) | {CODEC_RAW}
    by_name = {str(e["name"]): dict(e) for e in entries}
    raw_bytes = float(by_name[CODEC_RAW]["bytes"]) if CODEC_RAW in by_name else float("inf")
    passing: list[dict[str, Any]] = []
    jpeg: dict[str, Any] | None = None
    for e in by_name.values():
        name = str(e["name"])
        if name in must:
            continue
        if e["lossy"]:
            if not fidelity.admits(e["top1_agreement"], float(e["rel_err"])):
                continue
            if name.startswith("jpeg"):
                if jpeg is None or e["bytes"] < jpeg["bytes"]:
                    jpeg = e
                continue
        elif e["bytes"] > (1.0 - MIN_SAVING_SHARE) * raw_bytes:
            continue
        passing.append(e)
    if jpeg is not None:
        passing.append(jpeg)
    chosen = [by_name[n] for n in by_name if n in must]
    room = max(0, MAX_CODECS_PER_CUT - len(chosen))
    chosen += sorted(passing, key=lambda e: e["bytes"])[:room]
    chosen.sort(key=lambda e: (e["name"] != CODEC_RAW, e["bytes"]))
    return chosen


def profile_codecs(
    model: SplitModel,
    frames: Sequence[Feeds],
    fidelity: Fidelity,
    required: Mapping[int, Iterable[str]] | None = None,
    advance: Callable[[], None] | None = None,
) -> dict[int, list[dict[str, Any]]]:
    """Measure every candidate codec of every cut of `model` on calibration `frames` (model
    feeds) and mark the actions: cut index → entries, each with `action: bool`. `required`
    names codecs to measure and keep per cut index (baselines); `advance` is called per cut."""
    if not frames:
        raise ValueError("codec profiling needs at least one calibration frame")
    required = required or {}
    references = [model.run_full(f) for f in frames]
    result: dict[int, list[dict[str, Any]]] = {}
    for k, cut in enumerate(model.partition.cuts):
        specs = model.cut_tensor_specs(k)
        crossings = [model.run_prefix(k, f) for f in frames]
        wanted = set(required.get(cut.index, ()))
        names = candidate_codecs(specs, fidelity)
        names += [n for n in sorted(wanted) if n not in names and _applies(n, specs)]

        def suffix(tensors: Mapping[str, np.ndarray], k: int = k) -> Mapping[str, np.ndarray]:
            return model.run_suffix(k, tensors)

        entries = measure_codecs(specs, crossings, references, suffix, names)
        chosen = {e["name"] for e in select_codecs(entries, fidelity, wanted)}
        result[cut.index] = [{**e, "action": e["name"] in chosen} for e in entries]
        if advance is not None:
            advance()
    return result
