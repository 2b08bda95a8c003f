"""Which (cut, codec) pairs are actions: bytes, encode/decode time and fidelity, measured.

A codec's worth depends on what crosses: a JPEG of a camera image is 1/50 of its raw float32,
the same codec on a feature map makes no sense, and a lossy codec is only an action if the
model's answer survives it. So each candidate codec of each cut is run on calibration frames
(real frames from the robot's source, so JPEG sizes are those of its camera) and measured:

- bytes on the wire (median and the 10th/90th percentiles: they follow the content),
- encode time (the robot's cost) and decode time (the cloud's), medians,
- fidelity against the uncompressed model, per output by its kind (`OutputKind`: declared in
  the model's metadata as `elasticfog.output.<name>`, else read from its shape and name): top-1
  agreement of classifier outputs (N×C with C ≥ 2), the relative L2 error of every other output
  (of its worst element for a distance output, e.g. zoo:stereo's d_coll), and for disparity-like
  outputs (a per-pixel map in pixels) the share of pixels off by more
  than 1 px, a disparity present on one side only counting as off; the worst frame of each.

`Fidelity` (fleet.yaml `fidelity:`, `--fidelity` on the CLI) decides which lossy codecs are
actions; lossless codecs always are, when they save at least `MIN_SAVING_SHARE` of the raw
bytes. By default only images may cross lossy (JPEG at the lowest quality of the ladder whose
answers meet the bound): a feature map crosses lossy only with `lossy_features: true`.
A codec a baseline asks for by name (`cloud:jpeg80`) is measured and kept whatever the bound.

Video (`h264`, image crossings, tried with `video: true` or when named): the calibration frames
are coded as one stream, as a camera's frames would be (the first a keyframe, the others
P-frames), and decoded in order; its fidelity is measured on every decoded frame like JPEG's,
`bytes`, `encode_ms` and `decode_ms` are the P-frames' and `key_bytes` the median keyframe (each
frame also coded alone). The calibration frames are some frames apart, so their P-frames are
bigger than a running camera's: the policy learns the real ones as it sends them.

The result is one list per cut of the profile's `codecs` entries
(`{name, bytes, bytes_p10, bytes_p90, encode_ms, decode_ms, top1_agreement, rel_err,
bad_pixel_share, lossy}`, and `key_bytes` for video; a measure with no output of its kind is
null), raw first;
`robotd.policies.CutTable` turns every entry into an action.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from common.defaults import DEFAULT_MAX_BAD_PIXEL_SHARE, DEFAULT_MAX_OUTPUT_REL_ERR
from common.errors import UserError
from common.partition import TensorSpec
from common.wire import WireError
from common.wire.tensor_codecs import (
    CODEC_RAW,
    decode_encoded,
    encode_tensor_as,
    image_hwc,
    parse_codec,
)
from common.wire.video_codec import (
    CODEC_H264,
    DEFAULT_CRF,
    H264Decoder,
    H264Encoder,
    encode_keyframe,
)

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
# A disparity off by more than this many pixels is a bad pixel (Middlebury's bad-1).
BAD_PIXEL_THRESHOLD_PX = 1.0
# Reference values below this magnitude are taken as this in relative errors of one element.
MIN_REFERENCE = 1e-6
# Model metadata key naming an output's kind: `elasticfog.output.d_coll` = `distance`.
OUTPUT_KIND_PREFIX = "elasticfog.output."

Feeds = dict[str, np.ndarray]


class OutputKind(str, Enum):
    """How a lossy crossing is judged on one model output."""

    CLASSIFIER = "classifier"  # N×C scores: the top-1 class must stay
    DISPARITY = "disparity"  # a per-pixel map in pixels: bad-1 share and relative error
    # A distance per element (zoo:stereo's d_coll, metres per curvature bin): the largest
    # relative error of one element, so a bin whose obstacle vanished is not averaged away.
    DISTANCE = "distance"
    VALUE = "value"  # anything else: relative L2 error


def output_kind(name: str, shape: Sequence[int], declared: Mapping[str, OutputKind]) -> OutputKind:
    """The kind of output `name` of `shape`: declared by the model, else N×C (C ≥ 2) is a
    classifier's, a name with `disparity` a disparity map, anything else a value."""
    if name in declared:
        return declared[name]
    if len(shape) == 2 and shape[1] >= 2:
        return OutputKind.CLASSIFIER
    if "disparity" in name.lower():
        return OutputKind.DISPARITY
    return OutputKind.VALUE


def declared_output_kinds(model_path: str | Path) -> dict[str, OutputKind]:
    """{output name: kind} the ONNX model declares in its metadata (`OUTPUT_KIND_PREFIX`);
    UserError for a kind that does not exist."""
    import onnx

    model = onnx.load(str(model_path), load_external_data=False)
    found: dict[str, OutputKind] = {}
    for prop in model.metadata_props:
        if prop.key.startswith(OUTPUT_KIND_PREFIX):
            try:
                found[prop.key[len(OUTPUT_KIND_PREFIX) :]] = OutputKind(prop.value)
            except ValueError:
                known = ", ".join(k.value for k in OutputKind)
                raise UserError(
                    f"{model_path}: metadata {prop.key}: unknown output kind {prop.value!r} "
                    f"(known: {known})"
                ) from None
    return found


def relative_error(got: np.ndarray, want: np.ndarray) -> float:
    """||got − want|| / ||want|| (L2) over the elements finite on both sides (the absolute
    error when the reference is all zero)."""
    g = np.asarray(got, dtype=np.float64)
    w = np.asarray(want, dtype=np.float64)
    both = np.isfinite(g) & np.isfinite(w)
    norm = float(np.linalg.norm(w[both]))
    diff = float(np.linalg.norm(g[both] - w[both]))
    return diff / norm if norm > 0 else diff


def worst_relative_error(got: np.ndarray, want: np.ndarray) -> float:
    """The largest |got − want| / |want| of one element (inf where one side is finite and the
    other not: an obstacle that appeared or vanished)."""
    g = np.asarray(got, dtype=np.float64)
    w = np.asarray(want, dtype=np.float64)
    if g.size == 0:
        return 0.0
    if np.any(np.isfinite(g) != np.isfinite(w)):
        return float("inf")
    both = np.isfinite(g) & np.isfinite(w)
    if not both.any():
        return 0.0
    scale = np.maximum(np.abs(w[both]), MIN_REFERENCE)
    return float(np.max(np.abs(g[both] - w[both]) / scale))


def bad_pixel_share(got: np.ndarray, want: np.ndarray) -> float:
    """Share of pixels whose disparity is off by more than `BAD_PIXEL_THRESHOLD_PX`, a pixel
    with a disparity on one side only (NaN, inf or ≤ 0 on the other: no match) counting as off."""
    g = np.asarray(got, dtype=np.float64)
    w = np.asarray(want, dtype=np.float64)
    if g.size == 0:
        return 0.0
    have_g = np.isfinite(g) & (g > 0)
    have_w = np.isfinite(w) & (w > 0)
    both = have_g & have_w
    off = np.zeros(g.shape, dtype=bool)
    off[both] = np.abs(g[both] - w[both]) > BAD_PIXEL_THRESHOLD_PX
    off |= have_g != have_w
    return float(off.mean())


@dataclass(frozen=True)
class Fidelity:
    """How close to the uncompressed model a lossy codec must keep the answers.

    `min_top1_agreement` applies to classifier outputs, `max_output_rel_err` to every other
    output and `max_bad_pixel_share` to disparity-like ones too (`OutputKind`); a bound set to
    None admits no lossy codec where it would apply. `lossy_features` lets non-image tensors
    cross lossy (fp16, int8)."""

    def allows(self, name: str) -> bool:
        """True when the codec list (if any) lets `name` be tried."""
        return name == CODEC_RAW or self.codecs is None or name in self.codecs

    min_top1_agreement: float = 0.98
    max_output_rel_err: float | None = DEFAULT_MAX_OUTPUT_REL_ERR
    lossy_features: bool = False
    codecs: tuple[str, ...] | None = None
    """Only these codecs (and raw) are tried; None: every codec that applies."""
    max_bad_pixel_share: float | None = DEFAULT_MAX_BAD_PIXEL_SHARE
    video: bool = False
    """Image crossings may be h264 too (measured as a stream)."""
    crf: int = DEFAULT_CRF
    """The h264 streams' CRF (`video.crf` of the fleet file)."""

    def admits(
        self, top1: float | None, rel_err: float | None, bad_pixels: float | None = None
    ) -> bool:
        """True when measured answers meet the bound; each measure is None when the model has
        no output of its kind, and a measure whose bound is None fails (cannot be checked)."""
        if top1 is None and rel_err is None:
            return False  # nothing was compared
        if top1 is not None and top1 < self.min_top1_agreement:
            return False
        if rel_err is not None and (
            self.max_output_rel_err is None or rel_err > self.max_output_rel_err
        ):
            return False
        return bad_pixels is None or (
            self.max_bad_pixel_share is not None and bad_pixels <= self.max_bad_pixel_share
        )


def fidelity_of(config: FidelityConfig, crf: int = DEFAULT_CRF) -> Fidelity:
    """The codec profiler's bound from the fleet file's `fidelity:` section (and its `video.crf`,
    the CRF h264 is measured at); UserError for a codec name that does not exist."""
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
        max_bad_pixel_share=config.max_bad_pixel_share,
        video=config.video,
        crf=crf,
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
        if fidelity.video:
            names.append(CODEC_H264)
    else:
        names = [CODEC_RAW, "raw+zstd"]
        if fidelity.lossy_features:
            names += LOSSY_FEATURE_CODECS
    if fidelity.codecs is not None:
        names += [n for n in fidelity.codecs if n not in names]
    return [n for n in names if fidelity.allows(n) and codec_applies(n, specs)]


def codec_applies(name: str, specs: Sequence[TensorSpec]) -> bool:
    """Whether codec `name` can carry every tensor of a cut carrying `specs`."""
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
    bad: list[float] = field(default_factory=list)
    key_bytes: list[int] = field(default_factory=list)

    def entry(self) -> dict[str, Any]:
        sizes = np.asarray(self.bytes, dtype=np.float64)
        video = {"key_bytes": float(np.median(self.key_bytes))} if self.key_bytes else {}
        return {
            "name": self.name,
            "bytes": float(np.median(sizes)),
            "bytes_p10": float(np.percentile(sizes, 10)),
            "bytes_p90": float(np.percentile(sizes, 90)),
            "encode_ms": round(float(np.median(self.encode_s)) * MS_PER_S, 4),
            "decode_ms": round(float(np.median(self.decode_s)) * MS_PER_S, 4),
            "top1_agreement": float(np.mean(self.agree)) if self.agree else None,
            "rel_err": float(max(self.rel_err)) if self.rel_err else None,
            "bad_pixel_share": float(max(self.bad)) if self.bad else None,
            "lossy": self.lossy,
            **video,
        }


def measure_codecs(
    specs: Sequence[TensorSpec],
    crossings: Sequence[Mapping[str, np.ndarray]],
    references: Sequence[Mapping[str, np.ndarray]],
    suffix: Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]],
    names: Iterable[str],
    declared: Mapping[str, OutputKind] | None = None,
    crf: int = DEFAULT_CRF,
) -> list[dict[str, Any]]:
    """Every codec in `names` on one cut: `crossings[i]` are the cut's tensors of calibration
    frame i, `references[i]` the uncompressed model's outputs for it, `suffix` runs the rest of
    the model, `declared` the output kinds the model declares, `crf` a video codec's quality.
    Returns one profile entry per codec (see the module docstring)."""
    out = []
    for name in names:
        codec = parse_codec(name)
        m = _Measured(name, codec.lossy, [], [], [], [], [])
        if codec.video:
            _measure_stream(m, specs, crossings, references, suffix, declared or {}, crf)
            out.append(m.entry())
            continue
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
                agree, err, bad = compare_outputs(outputs, reference, declared or {})
                if agree is not None:
                    m.agree.append(agree)
                if err is not None:
                    m.rel_err.append(err)
                if bad is not None:
                    m.bad.append(bad)
        out.append(m.entry())
    return out


def _measure_stream(
    m: _Measured,
    specs: Sequence[TensorSpec],
    crossings: Sequence[Mapping[str, np.ndarray]],
    references: Sequence[Mapping[str, np.ndarray]],
    suffix: Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]],
    declared: Mapping[str, OutputKind],
    crf: int,
) -> None:
    """A video codec on one cut: the calibration frames coded as one stream per tensor (a
    keyframe, then P-frames) and decoded in order, the fidelity measured on every frame; the
    bytes and times recorded are the P-frames' (all frames' with a single one), `key_bytes`
    each frame coded alone as a keyframe."""
    encoders, decoders, shapes = {}, {}, {}
    for s in specs:
        hwc = image_hwc(s.shape)
        assert hwc is not None  # the codec applies to the cut (candidate_codecs)
        encoders[s.name] = H264Encoder(*hwc, crf=crf)
        decoders[s.name] = H264Decoder(*hwc)
        shapes[s.name] = hwc
    for i, (tensors, reference) in enumerate(zip(crossings, references, strict=True)):
        key = i == 0
        t0 = time.perf_counter()
        coded = {s.name: encoders[s.name].encode(tensors[s.name], keyframe=key)[0] for s in specs}
        t1 = time.perf_counter()
        decoded = {
            s.name: decoders[s.name]
            .decode(coded[s.name], keyframe=key, where=s.name)
            .reshape(s.shape)
            for s in specs
        }
        t2 = time.perf_counter()
        m.key_bytes.append(
            sum(len(encode_keyframe(tensors[s.name], shapes[s.name], crf)) for s in specs)
        )
        if not key or len(crossings) == 1:
            m.bytes.append(sum(len(d) for d in coded.values()))
            m.encode_s.append(t1 - t0)
            m.decode_s.append(t2 - t1)
        agree, err, bad = compare_outputs(suffix(decoded), reference, declared)
        if agree is not None:
            m.agree.append(agree)
        if err is not None:
            m.rel_err.append(err)
        if bad is not None:
            m.bad.append(bad)


def compare_outputs(
    outputs: Mapping[str, np.ndarray],
    reference: Mapping[str, np.ndarray],
    declared: Mapping[str, OutputKind] | None = None,
) -> tuple[bool | None, float | None, float | None]:
    """(top-1 agreement of every classifier output; the largest relative error of the other
    outputs, L2 over each output, of its worst element for a distance output; the largest bad-1
    share of the disparity-like ones), each None when the model has no output of that kind
    (`output_kind`)."""
    agree: bool | None = None
    worst: float | None = None
    bad: float | None = None
    for name, ref in reference.items():
        got = np.asarray(outputs[name], dtype=np.float64)
        want = np.asarray(ref, dtype=np.float64)
        kind = output_kind(name, want.shape, declared or {})
        if kind is OutputKind.CLASSIFIER:
            same = bool(np.array_equal(got.argmax(axis=1), want.argmax(axis=1)))
            agree = same if agree is None else agree and same
            continue
        if kind is OutputKind.DISTANCE:
            err = worst_relative_error(got, want)
        else:
            err = relative_error(got, want)
        worst = err if worst is None else max(worst, err)
        if kind is OutputKind.DISPARITY:
            share = bad_pixel_share(got, want)
            bad = share if bad is None else max(bad, share)
    return agree, worst, bad


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
            if not fidelity.admits(e["top1_agreement"], e["rel_err"], e.get("bad_pixel_share")):
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
    declared = declared_output_kinds(model.partition.full)
    references = [model.run_full(f) for f in frames]
    result: dict[int, list[dict[str, Any]]] = {}
    for k, cut in enumerate(model.partition.cuts):
        specs = model.cut_tensor_specs(k)
        crossings = [model.run_prefix(k, f) for f in frames]
        wanted = set(required.get(cut.index, ()))
        names = candidate_codecs(specs, fidelity)
        names += [n for n in sorted(wanted) if n not in names and codec_applies(n, specs)]

        def suffix(tensors: Mapping[str, np.ndarray], k: int = k) -> Mapping[str, np.ndarray]:
            return model.run_suffix(k, tensors)

        entries = measure_codecs(
            specs, crossings, references, suffix, names, declared, fidelity.crf
        )
        chosen = {e["name"] for e in select_codecs(entries, fidelity, wanted)}
        result[cut.index] = [{**e, "action": e["name"] in chosen} for e in entries]
        if advance is not None:
            advance()
    return result
