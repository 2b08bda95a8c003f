"""Segments among a learning policy's actions (fleet `cuts.segments`, policy `elastic`).

A split made with segments lists them in the robot's profile (`segments`: [[start, end], ...],
`robotd.robot_profile`); `actions_table` adds each as an action once per codec its start cut
crosses in (`CutTable.with_segments`): for `elastic` unless its `segments` param is false, and
in the simulator for every policy compared (a profile file that lists segments). A segment's
reply is its end cut's tensors (zoo:stereo's points: 900 KiB at 320×240, 3.5 MiB at 640×480,
against d_coll's 164 B), so the learner's context gets a fourth feature, the MB coming back
(`action_contexts`); only when some action is a segment, so the learners of other models keep
their three features and behave as before.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from common.errors import UserError
from common.wire.tensor_codecs import is_video
from robotd.policies.base import BYTES_PER_MB, CutTable, FloatArray
from robotd.policies.nav_options import SEGMENTS_KEY


def profile_segments(profile: Mapping[str, Any] | CutTable) -> list[tuple[int, int]]:
    """The (start, end) cut pairs of the split's segments a profile lists (none for a table:
    a `CutTable` already holds whatever segments it has). UserError for a malformed list."""
    if not isinstance(profile, Mapping):
        return []
    listed = profile.get(SEGMENTS_KEY) or []
    pairs: list[tuple[int, int]] = []
    for pair in listed:
        ok = isinstance(pair, (list, tuple)) and len(pair) == 2
        if not ok or not all(isinstance(c, int) and not isinstance(c, bool) for c in pair):
            raise UserError(
                f"profile: {SEGMENTS_KEY}: expected [start, end] cut pairs, got {pair!r}"
            )
        if not pair[0] < pair[1]:
            raise UserError(
                f"profile: {SEGMENTS_KEY}: a segment ends after it starts, got {pair!r}"
            )
        pairs.append((pair[0], pair[1]))
    return pairs


def actions_table(profile: Mapping[str, Any] | CutTable, segments: bool = True) -> CutTable:
    """The actions of `profile`, with the segments it lists when `segments` is true (`elastic`
    with its `segments` param; the simulator, for every policy it compares)."""
    cuts = CutTable.from_profile(profile)
    pairs = profile_segments(profile) if segments else []
    return cuts.with_segments(pairs) if pairs else cuts


def context_unit_bytes(cuts: CutTable) -> float:
    """The bytes of one unit of the context's first feature: a MB, or with video actions among
    the actions their largest keyframe (about one JPEG of the frame).

    The ridge prior (gamma·I) assumes features of order 1. Camera-image codecs at one cut send
    a few KB to tens of KB, 0.002 to 0.03 MB: in MB, seconds per MB are shrunk so hard that
    h264's P-frames and JPEG are predicted at one cost until hundreds of frames were answered
    (docs/video.md), and the smaller one is never taken. In keyframe units the two differ by
    about one unit. Without video actions the unit stays a MB, so the learners of other
    configurations behave as before."""
    video = [key for key, codec in zip(cuts.keys, cuts.codecs, strict=True) if is_video(codec)]
    return max(video) if video and max(video) > 0 else BYTES_PER_MB


def action_contexts(cuts: CutTable) -> FloatArray:
    """The learner's context of every offloading action, one row each: [bytes sent (in
    `context_unit_bytes`), share of the model left to the cloud, 1], and with segments among
    the actions a fourth column, MB returned (a segment's end-cut tensors; the model's outputs
    for the others)."""
    unit = context_unit_bytes(cuts)
    columns = [cuts.bytes / unit, cuts.cloud_s / cuts.full_s, np.ones(cuts.size)]
    if cuts.has_segments:
        columns.append(cuts.returned_bytes / BYTES_PER_MB)
    return np.column_stack(columns)
