"""Defaults that the fleet models (common.config) and the CLI's options share.

They live apart from common.config so that building the CLI (`elasticfog --help`) reads them
without importing pydantic and the wire codec.
"""

from __future__ import annotations

DEFAULT_REGISTRY_PORT = 7447
DEFAULT_FLEET = "default"
"""The fleet name (in every key) of a fleet file that names none."""
DEFAULT_CAMERA_SOURCE = "photo"
"""The frame source of a robot that names none: a camera panning over a real photograph."""
# Frames the (cut, codec) pairs are measured on (fleet.yaml `fidelity.calibration_frames`).
DEFAULT_CALIBRATION_FRAMES = 8
# The fidelity bound's defaults (fleet.yaml `fidelity:`), chosen from the measurements in
# docs/experiments.md ("A fidelity gate for every output"): an output that is not a classifier's
# may move by at most this relative error (L2; a distance output's worst element), a disparity
# map may have at most this share of its pixels off by more than 1 px.
DEFAULT_MAX_OUTPUT_REL_ERR = 0.05
DEFAULT_MAX_BAD_PIXEL_SHARE = 0.05
# Largest request the registry reads (fleet.yaml `registry.max_request_bytes`): its requests,
# telemetry and probe reports are a few hundred bytes, so anything near this is an attack or a bug.
DEFAULT_MAX_REQUEST_BYTES = 64 * 1024

ZOO_PREFIX = "zoo:"
"""A model spec naming a zoo entry (`zoo:NAME`) rather than an ONNX file."""

# The stereo camera zoo:stereo is built for when the fleet file has no `nav: camera:` section
# (fleet.yaml `nav.camera`; `nav.camera.CameraModel`): a common small stereo camera, 60°
# horizontal field of view and a 6 cm baseline, 0.30 m above the floor on a small indoor robot.
DEFAULT_STEREO_HFOV_DEG = 60.0
DEFAULT_STEREO_BASELINE_M = 0.06
DEFAULT_STEREO_HEIGHT_M = 0.30
