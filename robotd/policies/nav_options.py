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
Config: `policy: {kind: static, params: {option: N}}`, or `--policy option:N` on the CLI.
Options 1 and 3 send the camera pair and may name the codec it crosses in
(`params: {option: 1, codec: jpeg80}`, `--policy option:1:jpeg80`); options 2 and 4 send no
image, so a codec there is refused. The robot's profile says where the named cuts are, which
segments the split has and which codecs the pair may cross in (`robotd.robot_profile`; the robot
measures the option's codec at start, `robotd.calibration.required_codecs`); a model without the
named cut is refused, as is option 3 on a split made without segments (fleet `cuts.segments`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from common.errors import UserError
from common.wire import WireError
from common.wire.tensor_codecs import applies, codec_names_for
from common.yaml_files import format_validation_error
from robotd.policies.base import (
    PURE_ROBOT,
    RAW_CODEC,
    CutTable,
    Policy,
)
from robotd.policies.baselines import FixedPolicy
from robotd.policies.params import NoParams, parse_params

POINTS_CUT = "points"
"""The named cut between the stereo stages and the obstacle stage (3D points)."""
OPTION_PREFIX = "option:"
STATIC_KIND = "static"
"""`static` without a cut: the fleet file's form, the option in its params."""
OPTIONS = (1, 2, 3, 4)
PAIR_OPTIONS = (1, 3)
"""The options that send the camera pair (the lowest cut), the only crossing a codec is for."""
NAMED_CUTS_KEY = "named_cuts"
SEGMENTS_KEY = "segments"
"""Profile keys: {name: cut index} of the model's named cuts, and [[start, end], ...] of the
split's segments."""
_VIEW_DTYPE, _VIEW_SHAPE = "uint8", (1, 1, 1, 3)
"""A camera view as the model takes it (1×H×W×3 uint8); a codec's fit does not depend on H, W."""
PAIR_CODECS_TEXT = ", ".join(codec_names_for(_VIEW_DTYPE, _VIEW_SHAPE)) + " (Q 1..100, e.g. jpeg80)"


class OptionParams(BaseModel):
    """`static` without a cut: the navigation option, and the camera pair's codec."""

    model_config = ConfigDict(extra="forbid")

    option: int = Field(
        ge=1,
        le=4,
        description="The paper's offloading option: 1 all in the cloud, 2 points on the robot, "
        "3 stereo in the cloud (a segment), 4 all on the robot.",
    )
    codec: str = Field(
        default=RAW_CODEC,
        description="Codec the camera pair crosses in (options 1 and 3 only): raw, raw+zstd, "
        "png (lossless) or jpeg<Q> (e.g. jpeg80).",
    )

    @field_validator("codec")
    @classmethod
    def _an_image_codec(cls, name: str) -> str:
        try:
            fits = applies(name, _VIEW_DTYPE, _VIEW_SHAPE)
        except WireError:
            fits = False
        if not fits:
            # A custom error reads as the message alone (no "Value error, " in front).
            raise PydanticCustomError(
                "pair_codec",
                "unknown codec for the camera pair (uint8 images); known: {known}",
                {"known": PAIR_CODECS_TEXT},
            )
        return name

    @model_validator(mode="after")
    def _codec_needs_the_pair(self) -> OptionParams:
        if self.codec != RAW_CODEC and self.option not in PAIR_OPTIONS:
            raise PydanticCustomError(
                "pair_codec",
                "codec {codec}: only options 1 and 3 send the camera pair (option 2 sends the "
                "points raw, option 4 sends nothing)",
                {"codec": self.codec},
            )
        return self


def parse_option_spec(spec: str) -> OptionParams | None:
    """The option of `option:N` or `option:N:CODEC`; None for any other policy; UserError for a
    malformed one."""
    name = spec.strip().lower()
    if not name.startswith(OPTION_PREFIX):
        return None
    number, sep, codec = (part.strip() for part in name[len(OPTION_PREFIX) :].partition(":"))
    if not number.isdigit() or int(number) not in OPTIONS:
        raise UserError(
            f"policy {spec!r}: expected option:1, option:2, option:3 or option:4 (options 1 and "
            "3 may name the camera pair's codec, e.g. option:1:jpeg80)"
        )
    if sep and not codec:
        raise UserError(
            f"policy {spec!r}: needs a codec after the colon, e.g. option:{number}:jpeg80"
        )
    try:
        return OptionParams(option=int(number), codec=codec or RAW_CODEC)
    except ValidationError as exc:
        raise UserError(f"policy {spec!r}: {format_validation_error(exc, OptionParams)}") from None


def nav_option(spec: str, params: Mapping[str, Any] | BaseModel | None) -> OptionParams | None:
    """The navigation option policy `spec` names: `option:N[:CODEC]` (which takes no params),
    or `static` with `params: {option: N, codec: C}`; None for any other policy. UserError,
    one line, for a malformed spec or params."""
    name = spec.strip().lower()
    if name == STATIC_KIND:
        return parse_params(OptionParams, params, name)
    option = parse_option_spec(spec)
    if option is not None:
        parse_params(NoParams, params, name)
    return option


def option_policy(option: OptionParams, profile: Mapping[str, Any] | CutTable, name: str) -> Policy:
    """The fixed policy of navigation option `option` for this robot's profile."""
    cuts = CutTable.from_profile(profile)
    number, codec = option.option, option.codec
    named = profile.get(NAMED_CUTS_KEY) if isinstance(profile, Mapping) else None
    points = named.get(POINTS_CUT) if isinstance(named, Mapping) else None
    if not isinstance(points, int):
        raise UserError(
            f"policy {name} (navigation option {number}) needs a model whose metadata names "
            f"its {POINTS_CUT!r} cut (zoo:stereo does); this model names none"
        )
    if number == 2:
        return FixedPolicy(cuts, points, name)
    if number == 4:
        return FixedPolicy(cuts, PURE_ROBOT, name)
    start = min(cuts.indices)
    _check_pair_codec(cuts, start, option, name)
    if number == 1:
        return FixedPolicy(cuts, start, name, codec)
    segments = profile.get(SEGMENTS_KEY, []) if isinstance(profile, Mapping) else []
    if [start, points] not in [list(pair) for pair in segments]:
        raise UserError(
            f"policy {name} (navigation option 3) needs the segment from cut {start} to the "
            f"{POINTS_CUT!r} cut ({points}): set `cuts: {{segments: true}}` in the fleet file"
        )
    return FixedPolicy(cuts.with_segment(start, points, codec), start, name, codec, end=points)


def _check_pair_codec(cuts: CutTable, start: int, option: OptionParams, name: str) -> None:
    """UserError unless the profile has the pair's cut in the option's codec (the robot measures
    it at start; a profile from elsewhere may lack it)."""
    if (start, option.codec, None) in cuts.positions():
        return
    offered = [codec for cut, codec, end in cuts.positions() if cut == start and end is None]
    raise UserError(
        f"policy {name} (navigation option {option.option}): the profile has no codec "
        f"{option.codec} for the camera pair (cut {start}; it has {', '.join(offered)})"
    )
