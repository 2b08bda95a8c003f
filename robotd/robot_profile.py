"""The robot-side profile the policies start from, and the policy built from it.

At every start the robot times the whole model on itself (`robot_profile`: cheap, a few runs)
and splits that time between each cut's prefix and suffix by their FLOPs; the policies then
learn the robot's real speed online. The (cut, codec) actions come from the codec table measured
on the robot's own frame source (`robotd.calibration`, cached). A source whose frames arrive on
their own (`zenoh`, `ros2:`) has no frame at start: its robot starts from the table's defaults
(raw, and the codecs its policy names) and `FirstFramesRefinement` measures the table on the
first frames it serves, then hands the frame loop the policy built on it. `warm_up` runs every
session once first, so that allocation belongs to startup and not to the first frames.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.codec_profile import fidelity_of
from common.config import FleetConfig
from common.errors import UserError
from common.heap import release_freed_memory
from common.image_input import ImageInputs
from common.partition.named_cuts import named_cuts
from common.partition.runtime import SplitModel
from common.profiler import median_ms
from common.source_spec import SourceSpec, parse_source
from robotd.calibration import CodecCalibration, CodecTable, calibration_frames, required_codecs
from robotd.policies import Objective, Policy, make_policy
from robotd.policies.nav_options import NAMED_CUTS_KEY, SEGMENTS_KEY

log = logging.getLogger("robotd")

# Whole-model runs timed at startup for the robot-side profile (after the profiler's warm-up).
PROFILE_RUNS = 3
# Minimum whole-model time in a profile (the policies need a positive one).
MIN_PROFILE_MS = 1e-3


def robot_profile(
    model: SplitModel,
    feeds: dict[str, np.ndarray],
    runs: int = PROFILE_RUNS,
    codecs: Mapping[int, list[dict[str, Any]]] | None = None,
) -> dict[str, Any]:
    """The policies' profile of this robot, cheap enough for every start: the whole model's
    median time measured here, split between each cut's prefix and suffix by their FLOPs (the
    policies then learn the robot's real speed online). A cut without FLOP counts is split by
    its position. `codecs` (`robotd.calibration.codec_table`) gives each cut its measured
    codec entries; those marked `action` become the policy's (cut, codec) actions. The cuts the
    model names in its metadata and the split's segments are listed too (the navigation
    options need them)."""
    full_ms = max(median_ms(lambda: model.run_full(feeds), runs), MIN_PROFILE_MS)
    cuts = model.partition.cuts
    rows = []
    for k, cut in enumerate(cuts):
        total = cut.prefix_flops + cut.suffix_flops
        share = cut.prefix_flops / total if total > 0 else k / max(1, len(cuts))
        rows.append(
            {
                "index": cut.index,
                "bytes": max(1, cut.bytes),
                "prefix_ms": full_ms * share,
                "suffix_ms": full_ms * (1.0 - share),
            }
        )
    part = model.partition
    profile = {
        "digest": model.digest,
        "full_ms": full_ms,
        "cuts": rows,
        # Where the navigation options fall (`robotd.policies.nav_options`).
        NAMED_CUTS_KEY: named_cuts(part),
        SEGMENTS_KEY: [[seg.start, seg.end] for seg in part.segments],
    }
    return profile if codecs is None else with_codecs(profile, codecs)


def with_codecs(
    profile: dict[str, Any], codecs: Mapping[int, list[dict[str, Any]]]
) -> dict[str, Any]:
    """`profile` with each cut's codecs those of codec table `codecs` marked `action` (a cut
    the table lacks keeps its own); the rest of the profile is kept as it is (its times
    scaled or not)."""
    rows = [
        {**row, "codecs": [e for e in codecs[row["index"]] if e.get("action")]}
        if row["index"] in codecs
        else row
        for row in profile["cuts"]
    ]
    return {**profile, "cuts": rows}


def warm_up(model: SplitModel, feeds: dict[str, np.ndarray]) -> None:
    """Run every prefix and suffix once: the first run of an onnxruntime session allocates,
    and that cost belongs to startup, not to the first frames."""
    for k in range(model.num_cuts):
        sent = model.run_prefix(k, feeds)
        model.run_suffix(k, sent, feeds)


@dataclass(frozen=True)
class StartProfile:
    """The profile a robot's policy starts from and, when its codecs are still to be measured
    on the first frames it serves (a source fed over the session, nothing cached), the
    calibration that measures them (`FirstFramesRefinement`)."""

    profile: dict[str, Any]
    first_frames: CodecCalibration | None = None


def measured_profile(
    model: SplitModel,
    feeds: dict[str, np.ndarray],
    *,
    config: FleetConfig,
    inputs: ImageInputs,
    source_spec: str | SourceSpec,
    seed: int,
    threads: int,
    policy_spec: str,
) -> StartProfile:
    """This robot's profile, with the (cut, codec) actions measured on its own source: at
    once for a source it reads itself, on the first frames served for one fed over the session
    (meanwhile: the cached table, else the defaults, `CodecCalibration.defaults`)."""
    fidelity = config.fidelity
    lowest = min(cut.index for cut in model.partition.cuts)
    calibration = CodecCalibration(
        model,
        fidelity_of(fidelity, config.video.crf),
        required_codecs(policy_spec, lowest, fleet_params(policy_spec, config)),
        {
            "source": str(source_spec),
            "frames": fidelity.calibration_frames,
            "seed": seed,
            "threads": threads,
        },
    )
    if not parse_source(source_spec).needs_session:
        codecs = calibration.table(
            lambda: calibration_frames(source_spec, inputs, fidelity.calibration_frames, seed)
        )
        return StartProfile(robot_profile(model, feeds, codecs=codecs))
    cached = calibration.cached()
    if cached is not None:
        return StartProfile(robot_profile(model, feeds, codecs=cached))
    log.info(
        "codecs of source %s: measured on its first %d frames; raw until then",
        source_spec,
        fidelity.calibration_frames,
    )
    return StartProfile(
        robot_profile(model, feeds, codecs=calibration.defaults()), first_frames=calibration
    )


class FirstFramesRefinement:
    """The policy measured on the robot's first frames (a source fed over the session).

    `offer(feeds)` keeps each served frame's model feeds until `count` are held (then True);
    `refined(stop)` measures the codecs on them (`CodecCalibration.measure`: the fidelity gate,
    the cache) and returns the policy `build` makes of `profile` with the measured actions, or
    None when `stop` was set meanwhile. `profile` is the one the starting policy was built on
    (scaled for an emulated robot: only its codecs change)."""

    def __init__(
        self,
        calibration: CodecCalibration,
        profile: dict[str, Any],
        build: Callable[[dict[str, Any]], Policy],
        *,
        count: int,
        robot: str = "robot",
    ) -> None:
        self.calibration = calibration
        self.profile = profile
        self.build = build
        self.count = count
        self.robot = robot
        self.frames: list[dict[str, np.ndarray]] = []

    def offer(self, feeds: dict[str, np.ndarray]) -> bool:
        """Keep `feeds` (a served frame's) while fewer than `count` are held; True once the
        measurement has its frames."""
        if len(self.frames) < self.count:
            self.frames.append(feeds)
        return len(self.frames) >= self.count

    def refined(self, stop: threading.Event | None = None) -> Policy | None:
        """The policy on the codecs measured on the frames kept (None: stopped meanwhile)."""
        table: CodecTable | None = self.calibration.measure(self.frames, stop)
        self.frames = []
        # The measurement's runs leave their freed tensors resident, as the start's do.
        release_freed_memory(self.robot)
        if table is None:
            return None
        policy = self.build(with_codecs(self.profile, table))
        actions = [
            f"{index}:{e['name']}"
            for index, entries in sorted(table.items())
            for e in entries
            if e.get("action")
        ]
        log.info(
            "%s: codecs measured on the first %d frames served; policy %s now has actions %s",
            self.robot,
            self.count,
            policy.name,
            ", ".join(actions),
        )
        return policy


def build_policy(
    spec: str, config: FleetConfig, profile: dict[str, Any], objective: Objective
) -> Policy:
    """The policy named by `spec` (`--policy`, or the fleet's); the fleet's parameters apply
    only to the fleet's own policy kind."""
    spec = spec.strip()
    if spec.lower() == "oracle":
        raise UserError(
            "policy oracle needs the true costs, which only the simulator has "
            "(use it with `elasticfog sim`)"
        )
    return make_policy(spec, profile, fleet_params(spec, config), objective)


def fleet_params(spec: str, config: FleetConfig) -> dict[str, Any]:
    """The fleet's policy parameters when `spec` is the fleet's policy kind; none for another
    policy (`--policy` naming a different one), whose parameters they are not."""
    same = spec.strip().lower() == config.policy.kind.strip().lower()
    return config.policy.params if same else {}
