"""fleet.yaml `nav: camera:` (the stereo camera zoo:stereo is built for): every key optional with
the camera model's defaults, the geometry handed to the zoo as build options, unknown keys and
values out of range (or in the wrong unit) refused with the field named."""

from __future__ import annotations

from typing import Any

import pytest

from common.config import FleetConfig, fleet_from_dict
from common.errors import UserError
from nav import camera as nav_camera

BASE: dict[str, Any] = {
    "service": "nav",
    "model": "zoo:stereo",
    "deadline_s": 0.5,
    "latency_bound": {"seconds": 0.3},
}


def load(nav: Any) -> FleetConfig:
    return fleet_from_dict({**BASE, "nav": nav}, source="fleet.yaml")


def test_without_the_section_the_camera_is_the_models_default() -> None:
    cfg = fleet_from_dict(BASE)
    assert cfg.zoo_options == {
        "baseline_m": nav_camera.DEFAULT_BASELINE_M,
        "hfov_deg": nav_camera.DEFAULT_HFOV_DEG,
        "height_m": nav_camera.DEFAULT_HEIGHT_M,
    }
    assert cfg.zoo_options == {"baseline_m": 0.06, "hfov_deg": 60.0, "height_m": 0.30}
    assert load({}).zoo_options == load({"camera": {}}).zoo_options == cfg.zoo_options


def test_each_key_is_optional_and_whole_numbers_are_taken() -> None:
    cfg = load({"camera": {"hfov_deg": 90, "baseline_m": 0.12}})
    assert cfg.zoo_options == {"baseline_m": 0.12, "hfov_deg": 90.0, "height_m": 0.30}
    assert isinstance(cfg.nav.camera.hfov_deg, float)
    assert load({"camera": {"height_m": 1}}).nav.camera.height_m == 1.0
    # A service's view (what the daemons run on) keeps the fleet's camera.
    assert cfg.for_service("nav").zoo_options == cfg.zoo_options


@pytest.mark.parametrize(
    ("nav", "message"),
    [
        ({"camera": {"hfov": 90}}, "nav.camera.hfov: unknown key; did you mean 'hfov_deg'?"),
        ({"cam": {}}, "nav.cam: unknown key; did you mean 'camera'?"),
        ({"camera": {"baseline_m": 0}}, "nav.camera.baseline_m: the stereo baseline must be in"),
        ({"camera": {"baseline_m": 60}}, "(0, 2] m, got 60.0 (in metres: 0.06 for 6 cm)"),
        ({"camera": {"baseline_m": -0.06}}, "nav.camera.baseline_m: the stereo baseline"),
        ({"camera": {"hfov_deg": 1.05}}, "must be in 10..170 degrees, got 1.05 (in degrees"),
        ({"camera": {"hfov_deg": 180}}, "nav.camera.hfov_deg: the horizontal field of view"),
        ({"camera": {"height_m": 30}}, "nav.camera.height_m: the camera height above the floor"),
        ({"camera": {"height_m": 0}}, "must be in (0, 5] m, got 0.0"),
        ({"camera": {"height_m": "0.3"}}, "nav.camera.height_m: Input should be a valid number"),
        ({"camera": {"hfov_deg": True}}, "nav.camera.hfov_deg: Input should be a valid number"),
        ({"camera": {"baseline_m": float("nan")}}, "nav.camera.baseline_m: Input should be a"),
        ({"camera": [0.06, 60]}, "nav.camera: Input should be"),
    ],
)
def test_bad_camera_keys_and_values_are_named(nav: Any, message: str) -> None:
    with pytest.raises(UserError) as info:
        load(nav)
    assert str(info.value).startswith("fleet.yaml: nav.")
    assert message in str(info.value)
