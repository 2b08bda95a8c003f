"""The robot's (cut, codec) actions, measured on frames of its own source at start.

A codec's bytes and a lossy codec's effect on the answers depend on what the camera sees, so the
robot measures them (`common.codec_profile`) on `fidelity.calibration_frames` frames read from a
second instance of its source, opened and closed before the run's source (a camera is not held
twice; a file or synthetic source starts again from its first frame). Frames are spread over the
source's first frames (every `CALIBRATION_STRIDE`-th), so a moving camera shows some variety; a
recording shorter than that (a bag, a video that does not loop) gives its first frames, one
after the other.

The measurement is cached in the user cache directory, keyed by the model digest, the source, the
fidelity bound, the codecs the policy needs by name and the threads: a second start of the same
robot reads it back at once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from common.codec_profile import Fidelity, profile_codecs
from common.image_input import ImageInputs
from common.models import cache_dir, read_cached_json, write_cached_json
from common.partition.runtime import SplitModel
from common.source_spec import CameraSpec, SourceError, SourceSpec, calibration_source
from robotd.policies import RAW_CODEC, fixed_action
from robotd.policies.nav_options import nav_option
from robotd.sources.frame_sources import EndOfStream
from robotd.sources.opening import open_source_for
from robotd.sources.stereo_frame import StereoFrame

log = logging.getLogger(__name__)

CALIBRATION_STRIDE = 5
CALIBRATION_FORMAT = 1


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
    frame, except for a camera, whose frames are taken as they come; a source fed over Zenoh
    is measured on photographs, `common.source_spec.calibration_source`); a stereo source's
    views feed the model's inputs of their names."""
    source = calibration_source(source)
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


def codec_table(
    model: SplitModel,
    frames: Callable[[], list[dict[str, np.ndarray]]],
    fidelity: Fidelity,
    required: Mapping[int, list[str]],
    key: Mapping[str, Any],
) -> dict[int, list[dict[str, Any]]]:
    """Every cut's measured codec entries (cached under `key` plus the model digest);
    `frames()` is only called when nothing is cached."""
    material = json.dumps(
        {
            "format": CALIBRATION_FORMAT,
            "digest": model.digest,
            "fidelity": dataclasses.asdict(fidelity),
            "required": {str(k): sorted(v) for k, v in required.items()},
            **key,
        },
        sort_keys=True,
    )
    name = hashlib.sha256(material.encode()).hexdigest()[:24]
    path = cache_dir() / "codecs" / f"{model.digest[:16]}-{name}.json"
    cached = _read(path)
    if cached is not None:
        return cached
    log.info("measuring codecs on calibration frames (once per model, source and bound)")
    table = profile_codecs(model, frames(), fidelity, required)
    write_cached_json(path, {str(k): v for k, v in table.items()})
    return table


def _read(path: Path) -> dict[int, list[dict[str, Any]]] | None:
    data = read_cached_json(path)
    if not isinstance(data, dict) or not all(k.isdigit() for k in data):
        return None
    return {int(k): v for k, v in data.items()}
