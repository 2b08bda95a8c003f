"""The robot-side profile the policies start from, and the policy built from it.

At every start the robot times the whole model on itself (`robot_profile`: cheap, a few runs)
and splits that time between each cut's prefix and suffix by their FLOPs; the policies then
learn the robot's real speed online. The (cut, codec) actions come from the codec table measured
on the robot's own frame source (`robotd.calibration`, cached). `warm_up` runs every session
once first, so that allocation belongs to startup and not to the first frames.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from common.codec_profile import fidelity_of
from common.config import FleetConfig
from common.errors import UserError
from common.image_input import ImageInputs
from common.partition.named_cuts import named_cuts
from common.partition.runtime import SplitModel
from common.profiler import median_ms
from common.source_spec import SourceSpec
from robotd.calibration import calibration_frames, codec_table, required_codecs
from robotd.policies import Objective, Policy, make_policy
from robotd.policies.nav_options import NAMED_CUTS_KEY, SEGMENTS_KEY

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
        row: dict[str, Any] = {
            "index": cut.index,
            "bytes": max(1, cut.bytes),
            "prefix_ms": full_ms * share,
            "suffix_ms": full_ms * (1.0 - share),
        }
        if codecs is not None and cut.index in codecs:
            row["codecs"] = [e for e in codecs[cut.index] if e.get("action")]
        rows.append(row)
    part = model.partition
    return {
        "digest": model.digest,
        "full_ms": full_ms,
        "cuts": rows,
        # Where the navigation options fall (`robotd.policies.nav_options`).
        NAMED_CUTS_KEY: named_cuts(part),
        SEGMENTS_KEY: [[seg.start, seg.end] for seg in part.segments],
    }


def warm_up(model: SplitModel, feeds: dict[str, np.ndarray]) -> None:
    """Run every prefix and suffix once: the first run of an onnxruntime session allocates,
    and that cost belongs to startup, not to the first frames."""
    for k in range(model.num_cuts):
        sent = model.run_prefix(k, feeds)
        model.run_suffix(k, sent, feeds)


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
) -> dict[str, Any]:
    """This robot's profile, with the (cut, codec) actions measured on its own source."""
    fidelity = config.fidelity
    lowest = min(cut.index for cut in model.partition.cuts)
    codecs = codec_table(
        model,
        lambda: calibration_frames(source_spec, inputs, fidelity.calibration_frames, seed),
        fidelity_of(fidelity),
        required_codecs(policy_spec, lowest, fleet_params(policy_spec, config)),
        {
            "source": str(source_spec),
            "frames": fidelity.calibration_frames,
            "seed": seed,
            "threads": threads,
        },
    )
    return robot_profile(model, feeds, codecs=codecs)


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
