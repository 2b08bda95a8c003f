"""zoo:stereo built for the fleet's camera (fleet.yaml `nav: camera:`): the geometry is in the
cached file's name, so two geometries never share a file; the default geometry keeps today's
file, bytes and digest (existing caches stay valid); the model's metadata `nav.camera` states the
camera it was built for, and its d_coll for a rendered wall moves as depth = fx·B/d says. Every
place that resolves the fleet's model (the robot's and the clouds' split, `nav assist`) builds
the same file from the same fleet file."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from common import zoo
from common.config import FleetConfig, fleet_from_dict
from common.fleet_model import fleet_partition
from common.models import file_digest, resolve_model
from nav.camera import DEFAULT_FORWARD_M, CameraModel
from nav.curvature import CurvatureBins
from nav.zoo_entry import STEREO_FORMAT
from robotd.sources.stereo_geometry import model_camera
from tests.unit.test_nav_stereo_graph import shifted, texture

SHAPE = (3, 120, 160)  # D = 32 disparities: cheap to build and run
C, H, W = SHAPE
DEFAULTS = {"baseline_m": 0.06, "hfov_deg": 60.0, "height_m": 0.30}
WIDE = {"baseline_m": 0.12, "hfov_deg": 90.0, "height_m": 0.5}
# sha256 of zoo:stereo at 3x120x160 as the code before build options wrote it (onnx 1.23.2 of
# the lock). The default geometry must keep giving this file: the caches robots and clouds
# already hold, and the digest they match models by. A graph change bumps STEREO_FORMAT and
# this digest with it.
DEFAULT_DIGEST_120X160 = "1321689a9b0d381977ad3155b5166fcdba51fe50ab366ed926475bb68b7cb10b"


def fleet(camera: Mapping[str, Any] | None = None) -> FleetConfig:
    """A one-service fleet of zoo:stereo at SHAPE; `camera`: its `nav: camera:` section."""
    data: dict[str, Any] = {
        "service": "nav",
        "model": "zoo:stereo",
        "input_shape": list(SHAPE),
        "deadline_s": 0.5,
        "latency_bound": {"seconds": 0.3},
    }
    if camera is not None:
        data["nav"] = {"camera": dict(camera)}
    return fleet_from_dict(data)


def props(path: Path) -> dict[str, str]:
    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def straight_dcoll(path: Path, disparity_px: float) -> float:
    """d_coll of the straight-ahead bin for a textured wall seen with `disparity_px`."""
    left = texture(H, W, seed=3)
    right = shifted(left, disparity_px)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    d_coll = session.run(None, {"left": left[None], "right": right[None]})[0][0]
    centres = CurvatureBins().centres()
    return float(d_coll[np.argmin(np.abs(centres))])


def test_the_default_geometry_keeps_todays_file_and_digest() -> None:
    """Regression: build options must not move the default model (its cache name, its bytes)."""
    plain = resolve_model("zoo:stereo", SHAPE)
    given = resolve_model("zoo:stereo", SHAPE, DEFAULTS)
    from_fleet = resolve_model("zoo:stereo", SHAPE, fleet().zoo_options)
    assert plain.path.name == f"stereo-3x120x160-v{STEREO_FORMAT}.onnx"
    assert given.path == plain.path == from_fleet.path
    assert plain.digest == given.digest == from_fleet.digest
    if onnx.__version__ == "1.23.2":  # the pinned bytes are this onnx's serialization
        assert plain.digest == DEFAULT_DIGEST_120X160


def test_another_geometry_is_another_file_built_for_it() -> None:
    default = resolve_model("zoo:stereo", SHAPE)
    wide = resolve_model("zoo:stereo", SHAPE, WIDE)
    only_baseline = resolve_model("zoo:stereo", SHAPE, {"baseline_m": 0.12})
    assert wide.path.name == (
        f"stereo-3x120x160-baseline_m0.12-height_m0.5-hfov_deg90.0-v{STEREO_FORMAT}.onnx"
    )
    assert only_baseline.path.name == f"stereo-3x120x160-baseline_m0.12-v{STEREO_FORMAT}.onnx"
    assert len({default.digest, wide.digest, only_baseline.digest}) == 3
    assert file_digest(wide.path) == wide.digest
    # The metadata states the camera: fx = (W/2)/tan(hfov/2) = 80 px at 90°, centred.
    camera = model_camera(wide.path)
    assert camera is not None
    assert dataclasses.astuple(camera) == pytest.approx((80.0, 0.12, 79.5, 59.5, 0.5, 0.1))
    assert camera.forward_m == DEFAULT_FORWARD_M
    # Another value of one option is another name: no two geometries share a file.
    near = zoo.cache_file_name(zoo.get("stereo"), SHAPE, {"baseline_m": 0.1200001})
    assert near != wide.path.name and near != only_baseline.path.name


def test_options_a_zoo_model_does_not_take_are_left_out() -> None:
    """A fleet's camera means nothing to a CNN: zoo:vgg's file and name stay the same."""
    entry = zoo.get("vgg")
    assert zoo.options_for(entry, WIDE) == {}
    assert zoo.cache_file_name(entry, (3, 32, 32), WIDE) == zoo.cache_file_name(entry, (3, 32, 32))


def test_d_coll_moves_as_fx_times_baseline_over_disparity() -> None:
    """A wall seen with the same disparity by two cameras: each model puts it at its own
    fx·B/d (plus the camera's offset ahead of the axle)."""
    disparity_px = 8.0
    for options in (DEFAULTS, WIDE):
        path = resolve_model("zoo:stereo", SHAPE, options).path
        camera = CameraModel.for_image(W, H, options["hfov_deg"], options["baseline_m"])
        want = camera.depth_m(disparity_px) + camera.forward_m
        assert straight_dcoll(path, disparity_px) == pytest.approx(want, abs=0.03), options
    # 138.6 px · 0.06 m / 8 = 1.04 m; 80 px · 0.12 m / 8 = 1.2 m


def test_the_fleets_model_is_built_for_its_camera_everywhere() -> None:
    """Robot and clouds split the fleet's model through `fleet_partition`; `nav assist` resolves
    it itself: the same file and digest from the same fleet file, for its nav.camera."""
    from nav.assist import _model_props

    small = {"input_shape": [3, 48, 64]}
    cfg = fleet(WIDE).model_copy(update=small)
    part = fleet_partition(cfg)
    want = resolve_model("zoo:stereo", (3, 48, 64), WIDE)
    assert part.digest == want.digest
    assert model_camera(part.full) == model_camera(want.path)
    assert fleet_partition(fleet().model_copy(update=small)).digest != part.digest
    assert (
        _model_props(fleet(WIDE))["nav.camera"]
        == props(resolve_model("zoo:stereo", SHAPE, WIDE).path)["nav.camera"]
    )
