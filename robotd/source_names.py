"""The names in a `--source` spec (synthetic, photo, video:PATH, camera:N, stereo:..., zenoh,
ros2:...) and the default one, and which sources need the daemon's Zenoh session.

They live apart from robotd.sources (cv2, numpy, the partitioner) so that an option's default can
name a source without importing them: `elasticfog --help` must stay fast.
"""

from __future__ import annotations

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
