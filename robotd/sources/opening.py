"""Opening a frame source: a spec (`common.source_spec`, parsed once) to the `FrameSource` that
yields its frames, at the model's input size.

One function per step: `open_source` opens a parsed spec (one case per kind: a new kind of
`common.source_spec.KINDS` gets its case here), `open_source_for` opens it at the size of a
model's image inputs and checks that its views feed them. The stereo and maneuver sources
belong to the navigation app (`nav.stereo_sources`), which registers its opener in the
`elasticfog.sources` entry point group: the robot daemon never imports an application.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from common.errors import UserError
from common.image_input import ImageInputs
from common.source_spec import (
    BagSpec,
    CameraSpec,
    PhotoSpec,
    Ros2Spec,
    SourceError,
    SourceSpec,
    StereoManeuverSpec,
    StereoPairSpec,
    StereoWorldSpec,
    SyntheticSpec,
    VideoSpec,
    ZenohSpec,
    parse_source,
)
from robotd.sources.frame_sources import (
    CameraSource,
    FrameSource,
    PhotoSource,
    SourceSession,
    SyntheticSource,
    VideoSource,
)

if TYPE_CHECKING:
    from robotd.sources.stereo_geometry import ModelCamera

SOURCE_ENTRY_POINT_GROUP = "elasticfog.sources"


def registered_opener(kind: str, spec: str) -> Callable[..., FrameSource]:
    """The opener an application on the runtime registered for source `kind` (entry point group
    `elasticfog.sources`; the robot daemon never imports an application). SourceError, naming
    the spec, when none is installed."""
    for ep in entry_points(group=SOURCE_ENTRY_POINT_GROUP, name=kind):
        opener: Callable[..., FrameSource] = ep.load()
        return opener
    raise SourceError(
        f"source {spec!r}: no opener for {kind!r} sources is installed (entry point group "
        f"{SOURCE_ENTRY_POINT_GROUP}; the navigation app registers them: reinstall elasticfog)"
    )


def open_source(
    spec: str | SourceSpec,
    *,
    height: int,
    width: int,
    seed: int = 0,
    session: SourceSession | None = None,
    views: tuple[str, ...] | None = None,
    built_for: ModelCamera | None = None,
) -> FrameSource:
    """Open the source of `spec`; synthetic, photo, stereo and zenoh frames are made
    `height`×`width` (the model's input size). A source fed over Zenoh needs the daemon's
    `session`, and `views`, the model's image inputs when it has several. `built_for` is the
    camera a stereo model was built for: a ROS 2 stereo source warns when its CameraInfos say
    another. A SourceError names a spec that does not parse or a source that cannot be opened."""
    parsed = parse_source(spec)
    if parsed.needs_session and session is None:
        raise SourceError(
            f"source {parsed.text!r} receives its frames over Zenoh: it is opened by the robot "
            "daemon, on its session"
        )
    match parsed:
        case Ros2Spec(right=None):
            assert session is not None
            # Imported here: rosbags' type store is built only for a ROS 2 source.
            from robotd.sources.ros2 import Ros2Source

            return Ros2Source(parsed, session, session.stop, height=height, width=width)
        case Ros2Spec():
            assert session is not None
            from robotd.sources.ros2_stereo import Ros2StereoSource

            return Ros2StereoSource(
                parsed, session, session.stop, height=height, width=width, built_for=built_for
            )
        case SyntheticSpec():
            return SyntheticSource(
                height,
                width,
                seed=seed,
                **_given(key_fraction=parsed.key_fraction, key_every=parsed.key_every),
            )
        case PhotoSpec():
            return PhotoSource(
                height,
                width,
                seed=seed,
                **_given(name=parsed.name, motion=parsed.motion, speed=parsed.speed),
            )
        case VideoSpec():
            return VideoSource(parsed.path, loop=parsed.loop)
        case BagSpec():
            # Imported here: rosbags is loaded only by a robot that reads a bag.
            from robotd.sources.bag import BagSource

            return BagSource(parsed.path, parsed.topic)
        case CameraSpec():
            return CameraSource(parsed.index, parsed.device)
        case StereoWorldSpec() | StereoPairSpec() | StereoManeuverSpec():
            # Registered by the navigation app, which builds them on its world and renderer.
            opener = registered_opener("stereo", parsed.text)
            return opener(parsed, height=height, width=width, seed=seed)
        case ZenohSpec():
            # Imported here: the wire's image decoders and a subscriber, for this kind only.
            from robotd.sources.zenoh_in import ZenohSource

            assert session is not None
            return ZenohSource(session, height=height, width=width, views=views)
    raise SourceError(f"source {parsed.text!r}: no opener for {type(parsed).__name__}")


def open_source_for(
    spec: str | SourceSpec,
    inputs: ImageInputs,
    *,
    seed: int = 0,
    session: SourceSession | None = None,
    built_for: ModelCamera | None = None,
) -> FrameSource:
    """`open_source` at the size of the model's image inputs (one fed over Zenoh on the daemon's
    `session`; `built_for`: the camera a stereo model was built for); a one-line UserError (and
    the source closed) when its frames do not feed them: a mono source on a model with several
    image inputs, a stereo source on a one-input model, views not named like the inputs."""
    source = open_source(
        spec,
        height=inputs.height,
        width=inputs.width,
        seed=seed,
        session=session,
        views=inputs.views,
        built_for=built_for,
    )
    try:
        inputs.check_views(source.views, str(spec).strip())
    except UserError:
        source.close()
        raise
    return source


def _given(**options: Any) -> dict[str, Any]:
    """The options a spec set (None: the source's own default)."""
    return {name: value for name, value in options.items() if value is not None}
