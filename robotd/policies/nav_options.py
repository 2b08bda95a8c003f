"""The navigation assistant's offloading options 1–4 (the paper's Section IV) as fixed actions,
for a model whose metadata names its `points` cut (zoo:stereo: `elasticfog.cut.points`):

| option | robot                        | cloud                          | action      |
| ------ | ---------------------------- | ------------------------------ | ----------- |
| 1      | sends the stereo pair        | cut 0 → d_coll                 | cut 0       |
| 2      | the pair → points            | points → d_coll                | cut points  |
| 3      | points → d_coll (the tail)   | cut 0 → points (a segment)     | segment     |
| 4      | everything                   | —                              | P           |

Shared control (joystick → command) stays on the robot in every option: it takes microseconds and
needs the freshest joystick and the robot's clock for the delay correction (docs/navigation.md).
Config: `policy: {kind: static, params: {option: N}}`, or `--policy option:N` on the CLI. The
robot's profile says where the named cuts are and which segments the split has
(`robotd.robot_profile`); a model without the named cut is refused, as is option 3 on a split
made without segments (fleet `cuts.segments`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from common.errors import UserError
from robotd.policies.base import PURE_ROBOT, CutTable, Policy
from robotd.policies.baselines import FixedPolicy

POINTS_CUT = "points"
"""The named cut between the stereo stages and the obstacle stage (3D points)."""
OPTION_PREFIX = "option:"
OPTIONS = (1, 2, 3, 4)
NAMED_CUTS_KEY = "named_cuts"
SEGMENTS_KEY = "segments"
"""Profile keys: {name: cut index} of the model's named cuts, and [[start, end], ...] of the
split's segments."""


class OptionParams(BaseModel):
    """`static` without a cut: the navigation option."""

    model_config = ConfigDict(extra="forbid")

    option: int = Field(
        ge=1,
        le=4,
        description="The paper's offloading option: 1 all in the cloud, 2 points on the robot, "
        "3 stereo in the cloud (a segment), 4 all on the robot.",
    )


def parse_option_spec(spec: str) -> int | None:
    """N of `option:N`; None for any other policy; UserError for a malformed one."""
    name = spec.strip().lower()
    if not name.startswith(OPTION_PREFIX):
        return None
    value = name[len(OPTION_PREFIX) :].strip()
    if not value.isdigit() or int(value) not in OPTIONS:
        raise UserError(f"policy {spec!r}: expected option:1, option:2, option:3 or option:4")
    return int(value)


def option_policy(option: int, profile: Mapping[str, Any] | CutTable, name: str) -> Policy:
    """The fixed policy of navigation option `option` for this robot's profile."""
    cuts = CutTable.from_profile(profile)
    named = profile.get(NAMED_CUTS_KEY) if isinstance(profile, Mapping) else None
    points = named.get(POINTS_CUT) if isinstance(named, Mapping) else None
    if not isinstance(points, int):
        raise UserError(
            f"policy {name} (navigation option {option}) needs a model whose metadata names "
            f"its {POINTS_CUT!r} cut (zoo:stereo does); this model names none"
        )
    if option == 1:
        return FixedPolicy(cuts, min(cuts.indices), name)
    if option == 2:
        return FixedPolicy(cuts, points, name)
    if option == 4:
        return FixedPolicy(cuts, PURE_ROBOT, name)
    start = min(cuts.indices)
    segments = profile.get(SEGMENTS_KEY, []) if isinstance(profile, Mapping) else []
    if [start, points] not in [list(pair) for pair in segments]:
        raise UserError(
            f"policy {name} (navigation option 3) needs the segment from cut {start} to the "
            f"{POINTS_CUT!r} cut ({points}): set `cuts: {{segments: true}}` in the fleet file"
        )
    return FixedPolicy(cuts.with_segment(start, points), start, name, end=points)
