"""The grammar of a frame source spec (`--source`, a machine's `source:`), parsed once into a typed
value, and the default source.

A spec is `KIND`, `KIND:ARGS` or `KIND,ARGS`; `parse_source` reads the kind and hands the rest to
that kind's parser in `KINDS`, which returns a frozen `SourceSpec` (a subclass per kind, its
options typed and checked) or raises a `SourceError` naming the spec and what is wrong. An unknown
kind is an error listing the known kinds and their forms. The config (when the fleet file loads)
and the robot (`--source`) both go through `parse_source`; `robotd.sources.opening.open_source`
opens the parsed value.

To add a kind: a `SourceSpec` subclass with its typed fields, a parser `(spec, args) -> that
subclass`, one `SourceKind` entry in `KINDS` (its name, its form for the error, its parser), and
the opener's case in `robotd.sources.opening`. A kind whose spec holds file paths overrides
`SourceSpec.resolved` so that the fleet file's relative paths are relative to the file.

This module imports neither cv2 nor numpy (only a `photo:NAME` spec imports `common.photos` to
check the name), so that an option's default can name a source and `elasticfog --help` stays fast.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from common import rmw_zenoh
from common.defaults import DEFAULT_CAMERA_SOURCE as DEFAULT_CAMERA_SOURCE  # re-exported
from common.errors import UserError

SYNTHETIC = "synthetic"
PHOTO = "photo"
assert DEFAULT_CAMERA_SOURCE == PHOTO  # the demo's and benchmarks' source looks like a camera
VIDEO_PREFIX = "video:"
BAG_PREFIX = "bag:"
VIDEO_OPTIONS = ("loop",)
CAMERA_PREFIX = "camera:"
CAMERA_FORM = "camera:INDEX|/dev/videoINDEX"
# `camera:/dev/video0`, what a Linux user types first: the V4L2 device of index 0.
_VIDEO_DEVICE = re.compile(r"/dev/video(\d+)")
STEREO_PREFIX = "stereo:"
# `stereo:world`: pairs rendered in nav's world; `stereo:motorcycle`: Middlebury's real pair.
STEREO_WORLD = "world"
STEREO_MOTORCYCLE = "motorcycle"
# `stereo:maneuver:N`: maneuver N of the navigation circuit, driven live (`nav.maneuver_source`).
STEREO_MANEUVER = "maneuver"
# `zenoh`: frames an application publishes on `ef/<fleet>/in/<robot>` (`robotd.sources.zenoh_in`).
ZENOH = "zenoh"
# `ros2:<topic>[,OPTIONS]`: a ROS 2 image topic over rmw_zenoh's key space (`robotd.sources.ros2`).
ROS2 = "ros2"
ROS2_FORM = "ros2:TOPIC[,right=TOPIC][,slop_ms=N][,type=image|compressed][,domain=ID]"
# A stereo pair from two topics: left and right images within this many ms are one pair.
DEFAULT_STEREO_SLOP_MS = 10.0
ROS2_OPTIONS = ("type", "domain", "right", "slop_ms")
MANEUVER_FORM = "stereo:maneuver:N[:lap=L][:assist=on|off][:t_dead=S][:out=PATH]"
MANEUVER_OPTIONS = ("lap", "assist", "out", "t_dead")


class SourceError(UserError):
    """A frame source that cannot be parsed, opened or read."""


class CameraMotion(str, enum.Enum):
    """Which movements the virtual camera of the `photo` source (and a moving stereo pair)
    makes."""

    PAN = "pan"
    ZOOM = "zoom"
    SHAKE = "shake"
    MIXED = "mixed"


def motion_names() -> str:
    return ", ".join(m.value for m in CameraMotion)


# -- the typed values ----------------------------------------------------------------------------
@dataclass(frozen=True)
class SourceSpec:
    """A parsed source spec; `text` is the spec as written (what logs and caches name)."""

    text: str

    def resolved(self, resolve: Callable[[str], str]) -> SourceSpec:
        """This spec with its file paths passed through `resolve` (the fleet file makes them
        relative to itself); kinds without paths return themselves."""
        return self

    @property
    def needs_session(self) -> bool:
        """Whether the source receives its frames over the robot daemon's Zenoh session: it is
        opened once the session is open (`robotd.sources.frame_sources.SourceSession`), and is not
        opened a second time for the start's calibration frames (its codecs are measured on the
        first frames it serves, `robotd.robot_profile.FirstFramesRefinement`)."""
        return False

    def __str__(self) -> str:
        return self.text


@dataclass(frozen=True)
class SyntheticSpec(SourceSpec):
    """`synthetic[:key=F][,every=N]`; None: the source's default."""

    key_fraction: float | None = None
    key_every: int | None = None


@dataclass(frozen=True)
class PhotoSpec(SourceSpec):
    """`photo[:NAME][,motion=M][,speed=F]`; None: the source's default."""

    name: str | None = None
    motion: CameraMotion | None = None
    speed: float | None = None


@dataclass(frozen=True)
class VideoSpec(SourceSpec):
    """`video:PATH[,loop=true|false]`: loop (the default) starts the file again at its end;
    without, the run ends there."""

    path: Path = Path()
    loop: bool = True

    def resolved(self, resolve: Callable[[str], str]) -> VideoSpec:
        path = resolve(str(self.path))
        options = "" if self.loop else ",loop=false"
        return replace(self, text=f"{VIDEO_PREFIX}{path}{options}", path=Path(path))


@dataclass(frozen=True)
class BagSpec(SourceSpec):
    """`bag:PATH[:TOPIC]`: a rosbag2 folder or file; TOPIC (made absolute) None: the bag's one
    image topic."""

    path: Path = Path()
    topic: str | None = None

    def resolved(self, resolve: Callable[[str], str]) -> BagSpec:
        path = resolve(str(self.path))
        topic = "" if self.topic is None else f":{self.topic}"
        return replace(self, text=f"{BAG_PREFIX}{path}{topic}", path=Path(path))


@dataclass(frozen=True)
class CameraSpec(SourceSpec):
    """`camera:N` or `camera:/dev/videoN` (`device`: the path as written, None for an index);
    either way OpenCV opens the camera of index N."""

    index: int = 0
    device: str | None = None


@dataclass(frozen=True)
class StereoWorldSpec(SourceSpec):
    """`stereo:world[,speed=F]`."""

    speed: float | None = None


@dataclass(frozen=True)
class StereoPairSpec(SourceSpec):
    """`stereo:motorcycle[,OPTIONS]` (paths None) or `stereo:LEFT,RIGHT[,OPTIONS]`."""

    paths: tuple[Path, Path] | None = None
    motion: CameraMotion | None = None
    speed: float | None = None


@dataclass(frozen=True)
class StereoManeuverSpec(SourceSpec):
    """`stereo:maneuver:N[:lap=L][:assist=on|off][:t_dead=S][:out=PATH]`; t_dead None: the
    assistant's default."""

    maneuver: int = 0
    lap: int = 0
    assist: bool = True
    out: Path | None = None
    t_dead_s: float | None = None


@dataclass(frozen=True)
class ZenohSpec(SourceSpec):
    """`zenoh`: frames from `ef/<fleet>/in/<robot>`."""

    @property
    def needs_session(self) -> bool:
        return True


class Ros2FrameType(str, enum.Enum):
    """The message a `ros2:` source reads: `type=image` (sensor_msgs/msg/Image, the default) or
    `type=compressed` (sensor_msgs/msg/CompressedImage)."""

    IMAGE = "image"
    COMPRESSED = "compressed"


@dataclass(frozen=True)
class Ros2Spec(SourceSpec):
    """`ros2:<topic>[,right=<topic>][,slop_ms=N][,type=image|compressed][,domain=<id>]`;
    topics fully qualified, `domain` None: the robot's `ros2.domain_id`. With `right`, a stereo
    camera: `topic` is the left image, paired with the right one by header stamp within
    `slop_ms`."""

    topic: str = "/"
    type: Ros2FrameType = Ros2FrameType.IMAGE
    domain: int | None = None
    right: str | None = None
    slop_ms: float = DEFAULT_STEREO_SLOP_MS

    @property
    def topics(self) -> tuple[str, ...]:
        """The image topics read: the one, or left and right."""
        return (self.topic,) if self.right is None else (self.topic, self.right)

    @property
    def needs_session(self) -> bool:
        return True


# -- the kinds -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class SourceKind:
    """One kind of source: its name (the spec's first word), its forms for error messages, and
    its parser of `(spec, what follows the name and its ':' or ',')`."""

    name: str
    forms: str
    parse: Callable[[str, str], SourceSpec]
    separators: str = ":"
    """What may follow the name: `:` for most kinds, also `,` for `photo,motion=pan`."""


def _items(spec: str, text: str, sep: str = ",") -> list[tuple[str, str]]:
    """`name=value` items separated by `sep`, each with both parts."""
    pairs = []
    for item in text.split(sep):
        name, eq, value = (part.strip() for part in item.partition("="))
        if not eq or not value:
            raise SourceError(f"source {spec!r}: expected name=value options, got {item!r}")
        pairs.append((name, value))
    return pairs


def _unknown(spec: str, name: str, known: tuple[str, ...]) -> SourceError:
    return SourceError(f"source {spec!r}: unknown option {name!r}; known: {', '.join(known)}")


def _number(spec: str, name: str, value: str, kind: type[float] | type[int] = float) -> float:
    try:
        return kind(value)
    except ValueError:
        raise SourceError(f"source {spec!r}: {name}={value!r} is not a number") from None


def _motion(spec: str, value: str) -> CameraMotion:
    if value not in {m.value for m in CameraMotion}:
        raise SourceError(f"source {spec!r}: motion={value!r} is not one of {motion_names()}")
    return CameraMotion(value)


def _motion_speed(
    spec: str, items: list[tuple[str, str]], known: tuple[str, ...] = ("motion", "speed")
) -> tuple[CameraMotion | None, float | None]:
    motion: CameraMotion | None = None
    speed: float | None = None
    for name, value in items:
        if name not in known:
            raise _unknown(spec, name, known)
        if name == "motion":
            motion = _motion(spec, value)
        else:
            speed = _number(spec, name, value)
    return motion, speed


def _parse_synthetic(spec: str, args: str) -> SyntheticSpec:
    key: float | None = None
    every: int | None = None
    if args.strip():
        for name, value in _items(spec, args):
            if name == "key":
                key = _number(spec, name, value)
            elif name == "every":
                every = int(_number(spec, name, value, int))
            else:
                raise _unknown(spec, name, ("key", "every"))
    return SyntheticSpec(spec, key_fraction=key, key_every=every)


def _parse_photo(spec: str, args: str) -> PhotoSpec:
    name: str | None = None
    if not args.strip():
        return PhotoSpec(spec)
    first, _, rest = args.partition(",")
    if first.strip() and "=" not in first:
        # Imported here: it loads cv2, which a spec without a photograph's name does not need.
        from common.photos import PHOTOS

        name = first.strip()
        if name not in PHOTOS:
            raise SourceError(
                f"source {spec!r}: unknown photo {name!r}; known: {', '.join(PHOTOS)}"
            )
        args = rest
    motion, speed = _motion_speed(spec, _items(spec, args)) if args.strip() else (None, None)
    return PhotoSpec(spec, name=name, motion=motion, speed=speed)


def _parse_video(spec: str, args: str) -> VideoSpec:
    path, loop = args, True
    # Options follow the path after commas; a comma not followed by a known option is the path's.
    while True:
        head, comma, tail = path.rpartition(",")
        name, eq, value = (part.strip() for part in tail.partition("="))
        if not comma or not eq or name not in VIDEO_OPTIONS:
            break
        if value not in ("true", "false"):
            raise SourceError(f"source {spec!r}: loop={value!r}; expected true or false")
        loop, path = value == "true", head
    if not path.strip():
        raise SourceError(f"source {spec!r}: video needs a file, e.g. video:run.mp4")
    return VideoSpec(spec, path=Path(path.strip()).expanduser(), loop=loop)


# A ROS 2 topic name (after its leading `/`): tokens of letters, digits and `_` between `/`s, none
# starting with a digit (ROS 2's rules; `~` and substitutions are for launch files, not bags).
_TOPIC = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def _parse_bag(spec: str, args: str) -> BagSpec:
    """`PATH[:TOPIC]`: a topic holds no `:`, so the last `:` ends the path when a topic name
    follows it (a path with a `:` in it then needs the topic named)."""
    path, topic = args.strip(), None
    head, colon, tail = path.rpartition(":")
    if colon and _TOPIC.fullmatch(tail.strip().lstrip("/")):
        path, topic = head.strip(), "/" + tail.strip().lstrip("/")
    elif colon and tail.strip().startswith("/"):
        raise SourceError(
            f"source {spec!r}: {tail.strip()!r} is not a ROS 2 topic name (letters, digits and _ "
            "between /s)"
        )
    if not path:
        raise SourceError(f"source {spec!r}: bag needs a path, e.g. bag:run_0 or bag:run.mcap")
    return BagSpec(spec, path=Path(path).expanduser(), topic=topic)


def _parse_camera(spec: str, args: str) -> CameraSpec:
    text = args.strip()
    if text.isdigit():
        return CameraSpec(spec, index=int(text))
    device = _VIDEO_DEVICE.fullmatch(text)
    if device is None:
        raise SourceError(
            f"source {spec!r}: camera needs an index or a video device, e.g. camera:0 or "
            "camera:/dev/video0"
        )
    return CameraSpec(spec, index=int(device.group(1)), device=text)


STEREO_FORMS = (
    "stereo:world[,speed=F], stereo:motorcycle[,motion=M][,speed=F], "
    f"stereo:LEFT,RIGHT[,motion=M][,speed=F] or {MANEUVER_FORM}"
)


def _parse_stereo(spec: str, args: str) -> SourceSpec:
    if args.split(":", 1)[0].strip() == STEREO_MANEUVER:
        return _parse_maneuver(spec, args.strip()[len(STEREO_MANEUVER) :])
    items = [item.strip() for item in args.split(",")]
    if not items[0]:
        raise SourceError(f"source {spec!r}: expected {STEREO_FORMS}")
    if items[0] == STEREO_WORLD:
        _, speed = _motion_speed(
            spec, _items(spec, ",".join(items[1:])) if items[1:] else [], ("speed",)
        )
        return StereoWorldSpec(spec, speed=speed)
    if items[0] == STEREO_MOTORCYCLE:
        motion, speed = _motion_speed(spec, _items(spec, ",".join(items[1:])) if items[1:] else [])
        return StereoPairSpec(spec, motion=motion, speed=speed)
    if len(items) < 2 or not items[1] or "=" in items[1] or "=" in items[0]:
        raise SourceError(
            f"source {spec!r}: a pair of files needs two paths, stereo:LEFT,RIGHT; "
            f"expected {STEREO_FORMS}"
        )
    paths = (Path(items[0]).expanduser(), Path(items[1]).expanduser())
    motion, speed = _motion_speed(spec, _items(spec, ",".join(items[2:])) if items[2:] else [])
    return StereoPairSpec(spec, paths=paths, motion=motion, speed=speed)


def _parse_maneuver(spec: str, rest: str) -> StereoManeuverSpec:
    """`rest` is what follows `stereo:maneuver`."""
    items = rest.split(":")
    if items[0] != "" or len(items) < 2 or not items[1].strip().isdigit():
        raise SourceError(f"source {spec!r}: expected {MANEUVER_FORM}")
    options: dict[str, str] = {}
    for name, value in _items(spec, ":".join(items[2:]), ":") if items[2:] else []:
        if name not in MANEUVER_OPTIONS:
            raise _unknown(spec, name, MANEUVER_OPTIONS)
        options[name] = value
    lap_text = options.get("lap", "0")
    if not lap_text.isdigit():
        raise SourceError(f"source {spec!r}: lap={lap_text!r} is not a lap number (0, 1, ...)")
    assist = options.get("assist", "on")
    if assist not in ("on", "off"):
        raise SourceError(f"source {spec!r}: assist={assist!r}; expected on or off")
    out = options.get("out")
    return StereoManeuverSpec(
        spec,
        maneuver=int(items[1]),
        lap=int(lap_text),
        assist=assist == "on",
        out=None if out is None else Path(out).expanduser(),
        t_dead_s=_t_dead(spec, options.get("t_dead")),
    )


def _t_dead(spec: str, text: str | None) -> float | None:
    """`t_dead=S`: a positive, finite number of seconds; absent: None (the default)."""
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise SourceError(f"source {spec!r}: t_dead={text!r} is not a positive number of seconds")
    return value


def _parse_zenoh(spec: str, args: str) -> ZenohSpec:
    if args.strip():
        raise SourceError(f"source {spec!r}: zenoh takes no options (its key is the robot's)")
    return ZenohSpec(spec)


def _parse_ros2(spec: str, args: str) -> Ros2Spec:
    topic, *options = (part.strip() for part in args.split(","))
    try:
        parsed = Ros2Spec(spec, topic=rmw_zenoh.topic_name(topic))
    except UserError as exc:
        raise SourceError(f"source {spec!r}: {exc}") from None
    for name, value in _items(spec, ",".join(options)) if options else []:
        if name == "type":
            try:
                parsed = replace(parsed, type=Ros2FrameType(value))
            except ValueError:
                known = ", ".join(t.value for t in Ros2FrameType)
                raise SourceError(
                    f"source {spec!r}: type={value!r} is not one of {known}"
                ) from None
        elif name == "domain":
            try:
                parsed = replace(parsed, domain=rmw_zenoh.domain_id(value))
            except UserError as exc:
                raise SourceError(f"source {spec!r}: {exc}") from None
        elif name == "right":
            try:
                parsed = replace(parsed, right=rmw_zenoh.topic_name(value))
            except UserError as exc:
                raise SourceError(f"source {spec!r}: right={value!r}: {exc}") from None
        elif name == "slop_ms":
            slop = _number(spec, name, value)
            if not (math.isfinite(slop) and slop > 0):
                raise SourceError(f"source {spec!r}: slop_ms must be a positive number of ms")
            parsed = replace(parsed, slop_ms=slop)
        else:
            raise _unknown(spec, name, ROS2_OPTIONS)
    given = {n for n, _ in _items(spec, ",".join(options))} if options else set()
    if parsed.right is None and "slop_ms" in given:
        raise SourceError(f"source {spec!r}: slop_ms pairs a stereo camera's images: give right=")
    if parsed.right == parsed.topic:
        raise SourceError(f"source {spec!r}: left and right are both {parsed.topic}")
    return parsed


# The kinds, by name. A new kind is one entry here (and its opener in robotd.sources.opening).
KINDS: dict[str, SourceKind] = {
    kind.name: kind
    for kind in (
        SourceKind(SYNTHETIC, "synthetic[:key=F,every=N]", _parse_synthetic),
        SourceKind(
            PHOTO, "photo[:NAME][,motion=pan|zoom|shake|mixed][,speed=F]", _parse_photo, ":,"
        ),
        SourceKind("video", "video:PATH[,loop=false]", _parse_video),
        SourceKind("bag", "bag:PATH[:TOPIC]", _parse_bag),
        SourceKind("camera", CAMERA_FORM, _parse_camera),
        SourceKind("stereo", STEREO_FORMS, _parse_stereo),
        SourceKind(ZENOH, ZENOH, _parse_zenoh),
        SourceKind(ROS2, ROS2_FORM, _parse_ros2),
    )
}


def source_forms() -> str:
    """Every kind's forms, for an error or a help text."""
    forms = [kind.forms for kind in KINDS.values()]
    return ", ".join(forms[:-1]) + ", " + forms[-1] if len(forms) > 1 else forms[0]


def parse_source(spec: str | SourceSpec) -> SourceSpec:
    """The typed value of `spec`; a SourceError naming the spec, and for an unknown kind the
    known kinds and their forms."""
    if isinstance(spec, SourceSpec):
        return spec
    text = spec.strip()
    cut = min((i for i in (text.find(":"), text.find(",")) if i >= 0), default=len(text))
    kind = KINDS.get(text[:cut])
    if kind is None or (cut < len(text) and text[cut] not in kind.separators):
        raise SourceError(
            f"unknown frame source {text!r}; known kinds: {', '.join(KINDS)}; expected "
            f"{source_forms()}"
        )
    return kind.parse(text, text[cut + 1 :])


def needs_session(spec: str | SourceSpec) -> bool:
    """Whether source `spec` receives its frames over the daemon's Zenoh session."""
    return parse_source(spec).needs_session


def parse_ros2_source(spec: str | SourceSpec) -> Ros2Spec:
    """The typed value of a `ros2:` spec; a SourceError for any other."""
    parsed = parse_source(spec)
    if not isinstance(parsed, Ros2Spec):
        raise SourceError(f"source {str(spec)!r} is not a {ROS2_FORM} source")
    return parsed


def check_results_topics(source: str | SourceSpec, results_prefix: str | None, domain: int) -> None:
    """A UserError when the robot would publish its results on its own input: a `ros2:` source
    whose topic is the results prefix or below it, in the same domain (`domain`: the fleet's)."""
    parsed = parse_source(source)
    if results_prefix is None or not isinstance(parsed, Ros2Spec):
        return
    same_domain = (parsed.domain if parsed.domain is not None else domain) == domain
    for topic in parsed.topics:
        if same_domain and rmw_zenoh.is_within(topic, results_prefix):
            raise UserError(
                f"results topic prefix {results_prefix} collides with the input topic "
                f"{topic} of source {parsed.text!r}: the robot would read its own results; "
                "choose another prefix"
            )
