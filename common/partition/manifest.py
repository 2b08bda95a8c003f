"""A split directory's manifest: the tensor specs, the cuts and their files, read and written.

``manifest.json`` is the contract with the CLI's ``--json`` readers and with splits cached on
users' disks: its fields, ``MANIFEST_FORMAT`` and the file names below do not change without a
new format number. A directory holds ``manifest.json``, ``full.onnx``, ``weights.bin`` and
``cutNNN.prefix.onnx`` / ``cutNNN.suffix.onnx``; a split made with segments also holds
``cutAAA-BBB.segment.onnx`` (listed under ``segments``, a field older readers ignore).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import helper

from common.errors import UserError

MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.bin"
FULL_NAME = "full.onnx"
MANIFEST_FORMAT = 1


@dataclass(frozen=True)
class TensorSpec:
    """Name, numpy dtype name and static shape of one tensor (what the cloud validates)."""

    name: str
    dtype: str
    shape: tuple[int, ...]

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * np.dtype(self.dtype).itemsize

    def to_json(self) -> dict[str, Any]:
        return {"dtype": self.dtype, "shape": list(self.shape)}

    def value_info(self) -> onnx.ValueInfoProto:
        elem = helper.np_dtype_to_tensor_dtype(np.dtype(self.dtype))
        return helper.make_tensor_value_info(self.name, elem, list(self.shape))


@dataclass
class Cut:
    """One cut: the tensors crossing it, their bytes, and its prefix/suffix model files.

    ``prefix`` is None for cut 0 (the robot sends its inputs as they are). Excluded cuts have
    ``index == -1``, no files, and ``reason`` saying why.
    """

    index: int
    tensors: list[str]
    bytes: int
    prefix: Path | None
    suffix: Path | None
    verified: bool
    max_abs_err: float | None
    prefix_flops: int = 0
    suffix_flops: int = 0
    reason: str = ""


@dataclass
class Segment:
    """The part of the model between cut ``start`` and cut ``end`` (``start < end``): cut
    ``start``'s tensors in, cut ``end``'s out. The cloud runs it; the robot runs the prefix of
    ``start`` before and the suffix of ``end`` after (segment offload)."""

    start: int
    end: int
    path: Path
    verified: bool
    max_abs_err: float | None

    @property
    def label(self) -> str:
        return f"{self.start}-{self.end}"


def segment_file_name(start: int, end: int) -> str:
    """The file name of the segment from cut ``start`` to cut ``end`` in a split directory."""
    return f"cut{start:03d}-{end:03d}.segment.onnx"


def excluded_cut(tensors: Sequence[str], reason: str) -> Cut:
    """A cut left out of the split, with the reason (listed under ``excluded``)."""
    return Cut(-1, list(tensors), 0, None, None, False, None, reason=reason)


@dataclass
class Partition:
    """A split model on disk: the manifest's content with absolute paths."""

    dir: Path
    model: str
    digest: str
    inputs: list[str]
    outputs: list[str]
    specs: dict[str, TensorSpec]
    cuts: list[Cut]
    excluded: list[Cut] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)
    segments: list[Segment] = field(default_factory=list)

    @property
    def full(self) -> Path:
        return self.dir / FULL_NAME

    @property
    def weights(self) -> Path:
        return self.dir / WEIGHTS_NAME

    def cut(self, index: int) -> Cut:
        """Cut ``index``; ValueError naming the valid range otherwise."""
        if not 0 <= index < len(self.cuts):
            raise ValueError(f"unknown cut {index}: this model has cuts 0..{len(self.cuts) - 1}")
        return self.cuts[index]

    def cut_specs(self, index: int) -> list[TensorSpec]:
        return [self.specs[name] for name in self.cut(index).tensors]

    def segment(self, start: int, end: int) -> Segment:
        """The segment from cut ``start`` to cut ``end``; ValueError naming those there are."""
        for seg in self.segments:
            if (seg.start, seg.end) == (start, end):
                return seg
        known = ", ".join(s.label for s in self.segments) or "none (split without segments)"
        raise ValueError(f"no segment from cut {start} to cut {end}; this split has {known}")

    def has_segment(self, start: int, end: int) -> bool:
        return any((s.start, s.end) == (start, end) for s in self.segments)

    def files(self) -> list[Path]:
        """Every model file the split needs: the full model, its weights, each cut's models
        and each segment."""
        paths = [self.full, self.weights]
        for cut in self.cuts:
            paths += [p for p in (cut.prefix, cut.suffix) if p is not None]
        paths += [seg.path for seg in self.segments]
        return paths

    def manifest(self) -> dict[str, Any]:
        """The manifest.json content (the CLI contract), paths relative to the split directory."""

        def rel(p: Path | None) -> str | None:
            return None if p is None else p.relative_to(self.dir).as_posix()

        data: dict[str, Any] = {
            "format": MANIFEST_FORMAT,
            "model": self.model,
            "digest": self.digest,
            "inputs": list(self.inputs),
            "outputs": list(self.outputs),
            "cuts": [
                {
                    "index": c.index,
                    "tensors": list(c.tensors),
                    "bytes": c.bytes,
                    "prefix": rel(c.prefix),
                    "suffix": rel(c.suffix),
                    "verified": c.verified,
                    "max_abs_err": c.max_abs_err,
                    "prefix_flops": c.prefix_flops,
                    "suffix_flops": c.suffix_flops,
                }
                for c in self.cuts
            ],
            "excluded": [{"tensors": list(c.tensors), "reason": c.reason} for c in self.excluded],
            "specs": {name: spec.to_json() for name, spec in self.specs.items()},
            "full": FULL_NAME,
            "weights": WEIGHTS_NAME,
            "options": dict(self.options),
        }
        if self.segments:  # absent otherwise: manifests of splits without segments unchanged
            data["segments"] = [
                {
                    "start": s.start,
                    "end": s.end,
                    "path": rel(s.path),
                    "verified": s.verified,
                    "max_abs_err": s.max_abs_err,
                }
                for s in self.segments
            ]
        return data

    def write_manifest(self) -> None:
        """Write ``manifest.json`` whole or not at all (a temporary file renamed into place)."""
        tmp = self.dir / f".{MANIFEST_NAME}.tmp"
        tmp.write_text(json.dumps(self.manifest(), indent=2) + "\n")
        os.replace(tmp, self.dir / MANIFEST_NAME)

    @classmethod
    def load(cls, directory: Path) -> Partition:
        """Read ``directory/manifest.json``; UserError if it is missing or not ours."""
        directory = Path(directory)
        path = directory / MANIFEST_NAME
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict):
                raise TypeError(f"expected a JSON object, got {type(data).__name__}")
            if data.get("format") != MANIFEST_FORMAT:
                raise UserError(f"{path}: unsupported manifest format {data.get('format')!r}")
            specs = {name: _spec_from_json(name, s) for name, s in data["specs"].items()}
            cuts = [
                Cut(
                    index=int(c["index"]),
                    tensors=[str(t) for t in c["tensors"]],
                    bytes=int(c["bytes"]),
                    prefix=None if c["prefix"] is None else directory / c["prefix"],
                    suffix=directory / c["suffix"],
                    verified=bool(c["verified"]),
                    max_abs_err=None if c["max_abs_err"] is None else float(c["max_abs_err"]),
                    prefix_flops=int(c.get("prefix_flops", 0)),
                    suffix_flops=int(c.get("suffix_flops", 0)),
                )
                for c in data["cuts"]
            ]
            excluded = [
                excluded_cut([str(t) for t in c["tensors"]], str(c["reason"]))
                for c in data.get("excluded", [])
            ]
            segments = [
                Segment(
                    start=int(s["start"]),
                    end=int(s["end"]),
                    path=directory / s["path"],
                    verified=bool(s["verified"]),
                    max_abs_err=None if s["max_abs_err"] is None else float(s["max_abs_err"]),
                )
                for s in data.get("segments", [])
            ]
            return cls(
                dir=directory,
                model=str(data["model"]),
                digest=str(data["digest"]),
                inputs=[str(n) for n in data["inputs"]],
                outputs=[str(n) for n in data["outputs"]],
                specs=specs,
                cuts=cuts,
                excluded=excluded,
                options=dict(data.get("options", {})),
                segments=segments,
            )
        except FileNotFoundError:
            raise UserError(f"no split model in {directory} (missing {MANIFEST_NAME})") from None
        except OSError as exc:
            raise UserError(f"{path}: cannot read the split manifest ({exc.strerror})") from None
        # AttributeError (a list where a map belongs), ArithmeticError (a size of 1e400),
        # RecursionError (deep nesting): found by tests/unit/test_fuzz_partition.py.
        except (
            ValueError,
            KeyError,
            TypeError,
            AttributeError,
            ArithmeticError,
            RecursionError,
        ) as exc:
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise UserError(f"{path} is not a valid split manifest: {reason}") from None


def _spec_from_json(name: str, spec: Any) -> TensorSpec:
    """One `specs` entry, with a dtype numpy knows and sizes >= 0 (so `nbytes` is a size)."""
    dtype = str(spec["dtype"])
    np.dtype(dtype)  # TypeError for a name numpy does not know
    shape = tuple(int(d) for d in spec["shape"])
    if any(d < 0 for d in shape):
        raise ValueError(f"specs.{name}: sizes must be >= 0, got {list(shape)}")
    return TensorSpec(name, dtype, shape)
