"""The names in a `--source` spec (synthetic, photo, video:PATH, camera:N, stereo:..., zenoh,
ros2:...) and the default one, and which sources need the daemon's Zenoh session.

They live apart from robotd.sources (cv2, numpy, the partitioner) so that an option's default can
name a source without importing them: `elasticfog --help` must stay fast.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

from common import rmw_zenoh
from common.errors import UserError

SYNTHETIC = "synthetic"
PHOTO = "photo"
# The source the demo and the benchmarks use when none is given: it looks like a camera. Tests
# keep `synthetic` (their defaults do not change), whose entropy they control.
DEFAULT_CAMERA_SOURCE = PHOTO
VIDEO_PREFIX = "video:"
CAMERA_PREFIX = "camera:"
STEREO_PREFIX = "stereo:"
# `stereo:world`: pairs rendered in nav's world; `stereo:motorcycle`: Middlebury's real pair.
STEREO_WORLD = "world"
STEREO_MOTORCYCLE = "motorcycle"
# `stereo:maneuver:N`: maneuver N of the navigation circuit, driven live (`robotd.maneuver_source`).
STEREO_MANEUVER = "maneuver"
# `zenoh`: frames an application publishes on `ef/<fleet>/in/<robot>` (`robotd.zenoh_source`).
ZENOH = "zenoh"
# `ros2:<topic>[,OPTIONS]`: a ROS 2 image topic over rmw_zenoh's key space.
ROS2_PREFIX = "ros2:"


def needs_session(spec: str) -> bool:
    """Whether source `spec` receives its frames over the daemon's Zenoh session: such a source
    is opened once the session is open (`robotd.sources.SourceSession`), and cannot be opened a
    second time for the start's calibration frames."""
    spec = spec.strip()
    return spec == ZENOH or spec.startswith(ROS2_PREFIX)


def calibration_source(spec: str) -> str:
    """The source the start's codec measurement reads its frames from: the robot's own, except
    for a source fed over the session (no frame may have arrived yet, and frames taken for the
    measurement would be lost to the run), measured on the camera-like photographs instead."""
    return DEFAULT_CAMERA_SOURCE if needs_session(spec) else spec


class Ros2FrameType(str, enum.Enum):
    """The message a `ros2:` source reads: `type=image` (sensor_msgs/msg/Image, the default) or
    `type=compressed` (sensor_msgs/msg/CompressedImage)."""

    IMAGE = "image"
    COMPRESSED = "compressed"


@dataclass(frozen=True)
class Ros2SourceSpec:
    """A parsed `ros2:<topic>[,type=image|compressed][,domain=<id>]`; `domain` None: the fleet's
    `ros2.domain_id`."""

    topic: str
    type: Ros2FrameType = Ros2FrameType.IMAGE
    domain: int | None = None


def parse_ros2_source(spec: str) -> Ros2SourceSpec:
    """The topic and options of a `ros2:` source; a UserError naming what is wrong."""
    text = spec.strip()
    if not text.startswith(ROS2_PREFIX):
        raise UserError(f"source {spec!r} is not a ros2: source")
    topic, *options = (part.strip() for part in text[len(ROS2_PREFIX) :].split(","))
    try:
        parsed = Ros2SourceSpec(rmw_zenoh.topic_name(topic))
    except UserError as exc:
        raise UserError(f"source {spec!r}: {exc}") from None
    for item in options:
        name, sep, value = (part.strip() for part in item.partition("="))
        if not sep or not value:
            raise UserError(f"source {spec!r}: expected name=value options, got {item!r}")
        if name == "type":
            try:
                parsed = replace(parsed, type=Ros2FrameType(value))
            except ValueError:
                known = ", ".join(t.value for t in Ros2FrameType)
                raise UserError(f"source {spec!r}: type={value!r} is not one of {known}") from None
        elif name == "domain":
            try:
                parsed = replace(parsed, domain=rmw_zenoh.domain_id(value))
            except UserError as exc:
                raise UserError(f"source {spec!r}: {exc}") from None
        else:
            raise UserError(f"source {spec!r}: unknown option {name!r}; known: type, domain")
    return parsed


def check_results_topics(source: str, results_prefix: str | None, domain: int) -> None:
    """A UserError when the robot would publish its results on its own input: a `ros2:` source
    whose topic is the results prefix or below it, in the same domain (`domain`: the fleet's)."""
    if results_prefix is None or not source.strip().startswith(ROS2_PREFIX):
        return
    spec = parse_ros2_source(source)
    same_domain = (spec.domain if spec.domain is not None else domain) == domain
    if same_domain and rmw_zenoh.is_within(spec.topic, results_prefix):
        raise UserError(
            f"results topic prefix {results_prefix} collides with the input topic {spec.topic} "
            f"of source {source.strip()!r}: the robot would read its own results; choose another "
            "prefix"
        )
