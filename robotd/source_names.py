"""The names in a `--source` spec (synthetic, photo, video:PATH, camera:N, stereo:...) and the
default one.

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
