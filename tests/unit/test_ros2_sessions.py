"""Where a robot speaks ROS 2, checked without sessions: its ROS 2 settings (the fleet's `ros2`
under the machine's), the refusal of ROS 2 on a fleet session under access control, the ROS 2
session's Zenoh settings (the ROS 2 router only: no fleet endpoint, TLS file or access control),
and the model view's CameraInfo that maps results back onto the camera image."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from common.config import check_ros2_session, load_fleet
from common.errors import UserError
from common.ros2_messages import CameraInfo, Header, Roi
from common.session import ros2_settings
from robotd.results.ros2 import model_view_info
from robotd.ros2_node import InputFrame

CASES = Path(__file__).resolve().parents[1] / "config_cases"
MTLS_FLEET = CASES / "valid-ros2-beside-mtls-fleet.yaml"


def test_a_machines_ros2_section_wins_over_the_fleets() -> None:
    cfg = load_fleet(MTLS_FLEET)
    robot = cfg.ros2_for("robot-1")
    assert (robot.domain(), robot.qos_depth) == (3, 5)  # the fleet's
    assert (robot.endpoint, robot.namespace) == ("tcp/127.0.0.1:7447", "/robot1")  # its own
    assert cfg.ros2_for("edge-1").endpoint is None and cfg.ros2_for(None) == cfg.ros2


def test_ros2_on_a_fleet_session_under_access_control_is_refused(tmp_path: Path) -> None:
    data = yaml.safe_load(MTLS_FLEET.read_text())
    cfg = load_fleet(MTLS_FLEET)
    assert cfg.access_control
    check_ros2_session(cfg, "robot-1")  # it has an endpoint of its own
    del data["machines"]["robot-1"]["ros2"]
    data["machines"]["robot-1"]["source"] = "photo"
    data["machines"]["robot-1"].pop("results")
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data))
    cfg = load_fleet(path)  # nothing of ROS 2: fine
    with pytest.raises(UserError, match=r"set ros2\.endpoint .* machines\.robot-1\.ros2"):
        check_ros2_session(cfg, "robot-1", "ros2:/camera/image_raw")  # --source
    with pytest.raises(UserError, match="under access control"):
        check_ros2_session(cfg, "robot-1", None, "/elasticfog/robot_1")  # --results-ros2


def test_the_ros2_session_knows_nothing_of_the_fleet() -> None:
    cfg = load_fleet(MTLS_FLEET)
    settings = ros2_settings(cfg.ros2_for("robot-1"))
    assert settings["connect/endpoints"] == ["tcp/127.0.0.1:7447"]
    assert settings["listen/endpoints"] == ["tcp/127.0.0.1:0"]
    assert settings["mode"] == "peer" and settings["scouting/multicast/enabled"] is False
    assert not [k for k in settings if "tls" in k or "access_control" in k]
    remote = ros2_settings(cfg.ros2.model_copy(update={"endpoint": "tcp/10.0.0.1:7447"}))
    assert "listen/endpoints" not in remote
    with pytest.raises(UserError, match=r"ros2\.endpoint is not set"):
        ros2_settings(cfg.ros2)


HEADER = Header(1_700_000_000_000_000_000, "camera_optical")


def test_the_model_views_camera_info_maps_back_onto_the_camera() -> None:
    k = (500.0, 0.0, 319.5, 0.0, 500.0, 239.5, 0.0, 0.0, 1.0)
    p = (500.0, 0.0, 319.5, -30.0, 0.0, 500.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0)
    camera = CameraInfo(HEADER, 480, 640, k=k, p=p, d=(0.1,), distortion_model="plumb_bob")
    view = model_view_info(InputFrame(HEADER, 480, 640, camera), HEADER, 224, 224)
    # The centred 480×480 square of the 640×480 image, scaled to 224×224.
    assert view.header == HEADER and (view.height, view.width) == (224, 224)
    assert view.roi == Roi(80, 0, 480, 480)
    scale = 224 / 480
    assert view.fx == pytest.approx(500.0 * scale)
    # The principal point (the image centre) is the view's centre.
    assert view.cx == pytest.approx(111.5) and view.cy == pytest.approx(111.5)
    assert view.p[3] == pytest.approx(-30.0 * scale)  # −fx'·B: the same baseline
    assert (view.d, view.distortion_model) == ((0.1,), "plumb_bob")
    # No CameraInfo: the crop only, K zero (uncalibrated); a frame of no ROS 2 source: its own.
    bare = model_view_info(InputFrame(HEADER, 480, 640), HEADER, 224, 224)
    assert bare.roi == Roi(80, 0, 480, 480) and bare.k == (0.0,) * 9
    assert model_view_info(None, HEADER, 224, 224).roi == Roi(0, 0, 224, 224)
