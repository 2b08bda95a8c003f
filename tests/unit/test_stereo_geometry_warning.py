"""A ROS 2 stereo camera that is not the one zoo:stereo was built for (robotd/sources/
stereo_geometry.py): within 2% on fx and the baseline nothing is said; beyond, one warning names
both geometries and gives the `nav: camera:` lines, and those lines, put in the fleet file, build
a model the camera then matches; the robot hands its stereo source the camera its model states
in its metadata. The source's one warning on real sessions: tests/integration/
test_ros2_stereo_source.py."""

from __future__ import annotations

from typing import Any

import pytest
import yaml

from common import ros2_messages as rm
from common.config import fleet_from_dict
from common.errors import UserError
from common.models import resolve_model
from common.partition import load_partition
from common.partition.runtime import SplitModel
from robotd import robot_model
from robotd.robot_model import RobotModel
from robotd.sources.ros2_stereo import stereo_geometry
from robotd.sources.stereo_geometry import (
    ModelCamera,
    StereoGeometry,
    hfov_deg,
    mismatch_warning,
    model_camera,
)

T0 = 1_700_000_000_000_000_000
H, W = 120, 160
# zoo:stereo's default camera at 160x120: 60° (fx = 80/tan 30° = 138.6 px), 6 cm, 0.30 m.
DEFAULT_FX = 80 / (3**0.5 / 3)
BUILT = ModelCamera(DEFAULT_FX, 0.06, 79.5, 59.5, 0.30, 0.10)


def info(fx: float, p3: float = 0.0) -> rm.CameraInfo:
    """A 640x480 camera's CameraInfo (a right camera's with P[3] = −fx·B)."""
    k = (fx, 0.0, 319.5, 0.0, fx, 239.5, 0.0, 0.0, 1.0)
    p = (fx, 0.0, 319.5, p3, 0.0, fx, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0)
    return rm.CameraInfo(rm.Header(T0), 480, 640, k=k, p=p)


def seen(fx_px: float, baseline_m: float) -> StereoGeometry:
    return StereoGeometry(fx_px, 79.5, 59.5, baseline_m)


@pytest.mark.parametrize(("fx_scale", "baseline_m"), [(1.0, 0.06), (1.019, 0.06), (0.985, 0.0611)])
def test_a_camera_within_two_percent_is_the_models(fx_scale: float, baseline_m: float) -> None:
    assert (
        mismatch_warning(seen(DEFAULT_FX * fx_scale, baseline_m), BUILT, height=H, width=W) is None
    )


@pytest.mark.parametrize(("fx_scale", "baseline_m"), [(1.03, 0.06), (1.0, 0.0585), (0.6, 0.12)])
def test_a_camera_beyond_two_percent_is_named(fx_scale: float, baseline_m: float) -> None:
    warning = mismatch_warning(seen(DEFAULT_FX * fx_scale, baseline_m), BUILT, height=H, width=W)
    assert warning is not None
    assert f"fx {DEFAULT_FX * fx_scale:.1f} px in the model view 160x120" in warning
    assert f"baseline {baseline_m:.4f} m" in warning
    assert f"built for (fx {DEFAULT_FX:.1f} px, hfov 60.0 deg, baseline 0.0600 m)" in warning
    ratio = fx_scale * baseline_m / 0.06
    assert f"the true distances are {ratio:.2f}x those the model computes" in warning


def test_the_printed_lines_build_the_model_the_camera_matches() -> None:
    """The warning's `nav: camera:` lines, put in the fleet file, give a zoo:stereo whose
    metadata the same CameraInfos no longer contradict (fx from the hfov, B from P[3])."""
    fx, baseline_m = 415.0, 0.12  # at 640x480: 75.3°
    geometry = stereo_geometry(info(fx), info(fx, p3=-fx * baseline_m), H, W)
    warning = mismatch_warning(geometry, BUILT, height=H, width=W)
    assert warning is not None
    stanza = warning[warning.index("\nnav:") + 1 :]
    assert stanza == (
        "nav:\n  camera:\n    baseline_m: 0.12\n"
        f"    hfov_deg: {hfov_deg(fx / 4, W):.2f}\n    height_m: 0.3"
    )
    data: dict[str, Any] = {
        "service": "nav",
        "model": "zoo:stereo",
        "input_shape": [3, H, W],
        "deadline_s": 0.5,
        "latency_bound": {"seconds": 0.3},
        **yaml.safe_load(stanza),
    }
    cfg = fleet_from_dict(data)
    assert cfg.nav.camera.baseline_m == 0.12 and cfg.nav.camera.height_m == 0.3
    rebuilt = model_camera(resolve_model("zoo:stereo", (3, H, W), cfg.zoo_options).path)
    assert rebuilt is not None and rebuilt.fx_px == pytest.approx(fx / 4, rel=1e-3)
    assert mismatch_warning(geometry, rebuilt, height=H, width=W) is None


def test_the_models_camera_is_read_from_its_metadata() -> None:
    camera = model_camera(resolve_model("zoo:stereo", (3, H, W)).path)
    assert camera is not None
    assert (camera.fx_px, camera.baseline_m, camera.height_m) == pytest.approx(
        (DEFAULT_FX, 0.06, 0.30)
    )
    assert model_camera(resolve_model("zoo:vgg", (3, 32, 32)).path) is None
    with pytest.raises(UserError, match="expected six numbers"):
        ModelCamera.parse("1,2,3")


def test_the_robot_hands_a_stereo_source_its_models_camera(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    options = {"baseline_m": 0.12, "hfov_deg": 90.0, "height_m": 0.5}
    part = load_partition("zoo:stereo", input_shape=(3, 48, 64), zoo_options=options)
    robot = RobotModel(SplitModel(part, lazy=True), "zoo:stereo")
    given: dict[str, Any] = {}

    def opened(spec: str, inputs: object, **kwargs: Any) -> str:
        given.update(kwargs)
        return "source"

    monkeypatch.setattr(robot_model, "open_source_for", opened)
    assert robot.open_source("ros2:/left,right=/right", seed=0) == "source"
    built_for = given["built_for"]
    assert isinstance(built_for, ModelCamera) and built_for == model_camera(part.full)
    assert (built_for.baseline_m, built_for.height_m) == (0.12, 0.5)
    assert built_for.fx_px == pytest.approx(32.0)  # (64/2)/tan(45°)
