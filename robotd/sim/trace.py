"""Trace and profile files for the simulator: loading and validation.

A trace describes the conditions a robot goes through, segment by segment (contract):

    frames_per_second: 10
    noise: {jitter: 0.05}
    segments:
      - {frames: 1000, uplink_mbit: 10, downlink_mbit: 50, rtt_ms: 10, robot_cpu: 1.0,
         cloud_speedup: 8}

Optional keys: `entropy` (how per-frame entropy is drawn: `{kind: uniform, low, high}` (default
uniform 0.5..1.0), `{kind: constant, value}` or `{kind: video, path}` for real frames, the path
relative to the trace file), `deadline_ms` (the robot gives up on the cloud after this long and
finishes locally) and a `name` per segment. Unknown keys are errors, so a typo never silently
falls back to a default. Every problem is reported as one line naming the file and the field.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from common.errors import UserError
from common.yaml_files import format_validation_error, read_yaml
from robotd.policies.base import CutTable

# Unknown keys are errors; so are .inf and .nan, which YAML reads as floats and which every bound
# of the form `gt=0` lets through (tests/unit/test_fuzz_trace.py checks both).
_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)


class NoiseModel(BaseModel):
    """Randomness of the simulated times."""

    model_config = _STRICT

    jitter: float = Field(
        default=0.0,
        ge=0,
        le=1,
        description="σ of the multiplicative lognormal jitter (mean 1) applied to robot, uplink, "
        "cloud and downlink times independently.",
    )


class UniformEntropy(BaseModel):
    """Per-frame entropy drawn uniformly in [low, high]."""

    model_config = _STRICT

    kind: Literal["uniform"] = "uniform"
    low: float = Field(default=0.5, ge=0, le=1, description="Lowest normalized entropy.")
    high: float = Field(default=1.0, ge=0, le=1, description="Highest normalized entropy.")

    @model_validator(mode="after")
    def _ordered(self) -> UniformEntropy:
        if self.low > self.high:
            raise ValueError(f"low ({self.low}) must be <= high ({self.high})")
        return self


class ConstantEntropy(BaseModel):
    """The same entropy for every frame."""

    model_config = _STRICT

    kind: Literal["constant"]
    value: float = Field(ge=0, le=1, description="Normalized entropy of every frame.")


class VideoEntropy(BaseModel):
    """Entropy of real frames read from a video file (looped when shorter than the trace)."""

    model_config = _STRICT

    kind: Literal["video"]
    path: str = Field(min_length=1, description="Video file, relative to the trace file.")


EntropySource = Annotated[
    UniformEntropy | ConstantEntropy | VideoEntropy, Field(discriminator="kind")
]


class Segment(BaseModel):
    """Conditions held for a number of frames."""

    model_config = _STRICT

    frames: int = Field(ge=1, description="Number of frames in the segment.")
    uplink_mbit: float = Field(gt=0, description="Robot → cloud bandwidth, Mbit/s.")
    downlink_mbit: float = Field(gt=0, description="Cloud → robot bandwidth, Mbit/s.")
    rtt_ms: float = Field(ge=0, description="Round-trip time, ms (half counted each way).")
    robot_cpu: float = Field(
        gt=0, description="Robot speed relative to the profiling host (prefix_ms / robot_cpu)."
    )
    cloud_speedup: float = Field(gt=0, description="Cloud speed relative to the profiling host.")
    name: str | None = Field(default=None, description="Label for plots and tables.")


class Trace(BaseModel):
    """A whole trace: segments replayed in order."""

    model_config = _STRICT

    frames_per_second: float = Field(gt=0, description="Frame rate (time axis of the plots).")
    noise: NoiseModel = Field(default_factory=NoiseModel, description="Jitter.")
    entropy: EntropySource = Field(
        default_factory=UniformEntropy, description="How per-frame entropy is drawn."
    )
    deadline_ms: float | None = Field(
        default=None, gt=0, description="Give up on the cloud after this long (none: wait)."
    )
    segments: list[Segment] = Field(min_length=1, description="Segments, in order.")

    @property
    def total_frames(self) -> int:
        """Frames in the whole trace."""
        return sum(s.frames for s in self.segments)

    @property
    def segment_starts(self) -> list[int]:
        """First frame of every segment."""
        starts, at = [], 0
        for s in self.segments:
            starts.append(at)
            at += s.frames
        return starts


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{what} {path}: no such file") from None
    except IsADirectoryError:
        raise UserError(f"{what} {path}: is a directory") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{what} {path}: cannot read ({exc})") from None


def trace_from_dict(data: Any, source: str = "trace") -> Trace:
    """Validate a trace mapping; UserError naming the field on failure."""
    if not isinstance(data, dict):
        raise UserError(f"{source}: expected a mapping with frames_per_second and segments")
    try:
        return Trace.model_validate(data)
    except ValidationError as exc:
        raise UserError(f"{source}: {format_validation_error(exc, Trace)}") from None


def load_trace(path: str | Path) -> tuple[Trace, Path]:
    """Read and validate a trace YAML file; returns the trace and its resolved path."""
    file = Path(path)
    data = read_yaml(file, "trace")  # strict: a key given twice is refused, naming both lines
    return trace_from_dict(data, f"trace {file}"), file.resolve()


def load_profile(path: str | Path) -> tuple[CutTable, dict[str, Any]]:
    """Read and validate a profile JSON file (the partitioner's format)."""
    file = Path(path)
    text = _read_text(file, "profile")
    try:
        data = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)
    except json.JSONDecodeError as exc:
        raise UserError(
            f"profile {file}: not valid JSON ({exc.msg} at line {exc.lineno})"
        ) from None
    except ValueError as exc:  # a 5000-digit integer, a non-finite number
        raise UserError(f"profile {file}: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise UserError(f"profile {file}: not valid JSON (nested too deeply)") from None
    return CutTable.from_profile(data, f"profile {file}"), data


def _refuse_constant(name: str) -> float:
    """NaN and Infinity, which Python's json reads although JSON has no such values."""
    raise ValueError(f"{name} is not a number a profile may hold")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # e.g. 1e400
        raise ValueError(f"{text} is out of range for a float")
    return value


# Upper bound on frames read from a video, whatever the trace length (the entropies then loop).
MAX_VIDEO_FRAMES = 100_000


def video_entropies(path: Path, frames: int) -> np.ndarray:
    """Entropy of up to `frames` frames of a video file, looped to length `frames`."""
    import cv2  # only needed for video-driven traces

    from robotd.frame_path.entropy import frame_entropy

    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise UserError(f"trace entropy video {path}: cannot open")
        values: list[float] = []
        while len(values) < min(frames, MAX_VIDEO_FRAMES):
            ok, image = capture.read()
            if not ok:
                break
            values.append(frame_entropy(image))
    finally:
        capture.release()
    if not values:
        raise UserError(f"trace entropy video {path}: no frames could be read")
    return np.resize(np.array(values, dtype=np.float64), frames)
