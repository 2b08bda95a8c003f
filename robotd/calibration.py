"""The robot's (cut, codec) actions, measured on frames of its own source.

A codec's bytes and a lossy codec's effect on the answers depend on what the camera sees, so the
robot measures them (`common.codec_profile`) on `fidelity.calibration_frames` frames of its own
source. A source the robot reads itself (a file, a camera, synthetic frames) is measured at start
on a second instance of it, opened and closed before the run's source (a camera is not held
twice; a file or synthetic source starts again from its first frame). Frames are spread over the
source's first frames (every `CALIBRATION_STRIDE`-th), so a moving camera shows some variety; a
recording shorter than that (a bag, a video that does not loop) gives its first frames, one
after the other.

A source whose frames arrive on their own (`zenoh`, `ros2:`) has none at start, and a frame
taken for the measurement would be lost to the run: such a robot starts from `defaults` (raw, and
the codecs its policy names, never an untested lossy action) and measures on its own first frames
as they are served (`robotd.robot_profile.FirstFramesRefinement`). No source is measured on
packaged photographs: a robot installs the runtime lock, which has none.

The measurement is cached in the user cache directory, keyed by the model digest, the source, the
fidelity bound, the codecs the policy needs by name and the threads: a second start of the same
robot reads it back at once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.codec_profile import Fidelity, codec_applies, profile_codecs
from common.image_input import ImageInputs
from common.models import cache_dir, read_cached_json, write_cached_json
from common.partition.runtime import SplitModel
from common.source_spec import CameraSpec, SourceError, SourceSpec, parse_source
from common.wire.tensor_codecs import parse_codec
from robotd.policies import RAW_CODEC, fixed_action
from robotd.policies.nav_options import nav_option
from robotd.sources.frame_sources import EndOfStream
from robotd.sources.opening import open_source_for
from robotd.sources.stereo_frame import StereoFrame

log = logging.getLogger(__name__)

CALIBRATION_STRIDE = 5
CALIBRATION_FORMAT = 1

# Every cut's codec entries, by cut index (`common.codec_profile.profile_codecs`).
CodecTable = dict[int, list[dict[str, Any]]]


def required_codecs(
    policy_spec: str, lowest_cut: int, params: Mapping[str, Any] | None = None
) -> dict[int, list[str]]:
    """The codecs a baseline names, by cut index: `cloud:jpeg80` needs jpeg80 at the lowest
    cut, `static:3:int8` int8 at cut 3, a navigation option's codec (`option:1:png`, or
    `static` with `params`) the lowest cut's (the camera pair); other policies name none."""
    option = nav_option(policy_spec, params)
    if option is not None:
        return {} if option.codec == RAW_CODEC else {lowest_cut: [option.codec]}
    fixed = fixed_action(policy_spec)
    if fixed is None or fixed.codec == RAW_CODEC:
        return {}
    return {lowest_cut if fixed.cut is None else fixed.cut: [fixed.codec]}


def calibration_frames(
    source: str | SourceSpec, inputs: ImageInputs, count: int, seed: int
) -> list[dict[str, np.ndarray]]:
    """`count` model feeds from a fresh instance of `source` (every CALIBRATION_STRIDE-th
    frame, except for a camera, whose frames are taken as they come); a stereo source's views
    feed the model's inputs of their names. A source fed over the session has no second
    instance: it is measured on the run's first frames (`robotd.robot_profile`)."""
    source = parse_source(source)
    if source.needs_session:
        raise SourceError(
            f"source {source}: its frames arrive over the robot's session; the codecs are "
            "measured on the first frames it serves"
        )
    stride = 1 if isinstance(source, CameraSpec) else CALIBRATION_STRIDE
    frames = _read_feeds(source, inputs, count, stride, seed)
    if len(frames) < count and stride > 1:
        frames = _read_feeds(source, inputs, count, 1, seed)
    if not frames:
        raise SourceError(f"source {source}: no frame to measure the codecs on")
    return frames


def _read_feeds(
    source: SourceSpec, inputs: ImageInputs, count: int, stride: int, seed: int
) -> list[dict[str, np.ndarray]]:
    """Up to `count` feeds, every `stride`-th frame, fewer where the source ends first."""
    frames = []
    with open_source_for(source, inputs, seed=seed) as src:
        for i in range(count * stride):
            try:
                frame = src.read()
            except EndOfStream:
                break
            if i % stride == 0:
                frames.append(
                    inputs.feeds(frame.views if isinstance(frame, StereoFrame) else frame)
                )
    return frames


class _Stopped(Exception):
    """The daemon is stopping: a measurement under way is given up."""


@dataclass(frozen=True)
class CodecCalibration:
    """One robot's codec measurement: its model, the fidelity bound, the codecs its policy
    names by cut index (`required_codecs`), and what else keys the cache (`key`: the source, the
    frame count, the seed, the threads)."""

    model: SplitModel
    fidelity: Fidelity
    required: Mapping[int, Sequence[str]]
    key: Mapping[str, Any]

    @property
    def path(self) -> Path:
        """Where the measurement is cached (keyed by everything it depends on)."""
        material = json.dumps(
            {
                "format": CALIBRATION_FORMAT,
                "digest": self.model.digest,
                "fidelity": dataclasses.asdict(self.fidelity),
                "required": {str(k): sorted(v) for k, v in self.required.items()},
                **self.key,
            },
            sort_keys=True,
        )
        name = hashlib.sha256(material.encode()).hexdigest()[:24]
        return cache_dir() / "codecs" / f"{self.model.digest[:16]}-{name}.json"

    def cached(self) -> CodecTable | None:
        """The table measured at an earlier start, if the cache has it."""
        data = read_cached_json(self.path)
        if not isinstance(data, dict) or not all(k.isdigit() for k in data):
            return None
        return {int(k): v for k, v in data.items()}

    def table(self, frames: Callable[[], list[dict[str, np.ndarray]]]) -> CodecTable:
        """The cached table, else the one measured on `frames()` (then cached)."""
        cached = self.cached()
        if cached is not None:
            return cached
        table = self.measure(frames())
        assert table is not None  # nothing can stop it
        return table

    def measure(
        self, frames: list[dict[str, np.ndarray]], stop: threading.Event | None = None
    ) -> CodecTable | None:
        """Every cut's codecs measured on `frames` (model feeds) and cached; None when `stop`
        was set before the measurement ended (given up between cuts, nothing cached)."""
        log.info(
            "measuring codecs on %d calibration frames (once per model, source and bound)",
            len(frames),
        )

        def advance() -> None:
            if stop is not None and stop.is_set():
                raise _Stopped

        try:
            table = profile_codecs(self.model, frames, self.fidelity, self.required, advance)
        except _Stopped:
            return None
        write_cached_json(self.path, {str(k): v for k, v in table.items()})
        return table

    def defaults(self) -> CodecTable:
        """What a robot starts from before its frames are measured: every cut raw, and the
        codecs its policy names (kept whatever the bound, as when measured), their bytes
        taken as raw's until measured. No other codec is an action: a lossy one would not have
        passed the fidelity gate, a lossless one's saving is unknown."""
        table: CodecTable = {}
        for k, cut in enumerate(self.model.partition.cuts):
            specs = self.model.cut_tensor_specs(k)
            names = [RAW_CODEC, *(n for n in self.required.get(cut.index, ()) if n != RAW_CODEC)]
            table[cut.index] = [
                {
                    "name": name,
                    "bytes": float(max(1, cut.bytes)),
                    "encode_ms": 0.0,
                    "decode_ms": 0.0,
                    "lossy": parse_codec(name).lossy,
                    "measured": False,
                    "action": True,
                }
                for name in names
                if codec_applies(name, specs)
            ]
        return table
