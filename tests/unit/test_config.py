"""fleet.yaml: the valid cases load, every invalid case fails with one line naming the file and
the field (each invalid-*.yaml states the words it must produce on its `# expect:` line)."""

from __future__ import annotations

import typing
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from common import config as config_module
from common.config import FleetConfig, fleet_from_dict, load_fleet
from common.errors import UserError
from common.wire.registry import DeploymentState

CASES = Path(__file__).resolve().parents[1] / "config_cases"
VALID = sorted(CASES.glob("valid-*.yaml"))
INVALID = sorted(CASES.glob("invalid-*.yaml"))
EXPECT = "# expect: "


def test_there_are_cases() -> None:
    assert len(VALID) >= 4 and len(INVALID) >= 20


@pytest.mark.parametrize("path", VALID, ids=lambda p: p.stem)
def test_valid_cases_load(path: Path) -> None:
    config = load_fleet(path)
    assert isinstance(config, FleetConfig)
    assert config.source_path == path
    for robot in config.robot_ids:
        assert config.initial_service(robot) in config.deployment_ids


@pytest.mark.parametrize("path", INVALID, ids=lambda p: p.stem)
def test_invalid_cases_name_file_and_field(path: Path) -> None:
    first = path.read_text(encoding="utf-8").splitlines()[0]
    assert first.startswith(EXPECT), f"{path.name} needs a first line '{EXPECT}<words>'"
    expected = first[len(EXPECT) :]
    with pytest.raises(UserError) as info:
        load_fleet(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert expected in message
    assert "\n" not in message


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="no such file"):
        load_fleet(tmp_path / "fleet.yaml")
    with pytest.raises(UserError, match="is a directory"):
        load_fleet(tmp_path)


def test_defaults_and_resolved_paths() -> None:
    config = load_fleet(CASES / "valid-minimal.yaml")
    assert config.fleet == "default"
    assert config.registry.endpoint == "tcp/127.0.0.1:7447"
    assert config.registry.listen == ["tcp/0.0.0.0:7447"]
    assert config.registry.embedded_router is True
    assert config.latency_bound.stat == "median"
    assert config.latency_bound.window == 20
    assert config.latency_bound.hysteresis_s == 1.0
    assert config.latency_bound.better_margin == 0.2
    assert config.cuts.max_cut_tensors == 2 and config.cuts.names is None
    assert config.policy.kind == "elastic" and config.policy.params == {}
    assert config.objective.latency == 1.0 and config.objective.cpu == 0.0
    assert config.zenoh.lease_ms == 1000 and config.zenoh.shared_memory is True
    assert config.zoo_model == "vgg" and config.model_path is None
    # The RIB's sqlite file defaults to <fleet>.rib.sqlite next to the config file.
    assert config.db_path == CASES / "default.rib.sqlite"


def test_relative_paths_are_relative_to_the_file() -> None:
    config = load_fleet(CASES / "valid-fogros-shorthand.yaml")
    assert config.model_path == CASES / "models" / "net.onnx"
    assert config.machine("turtlebot").source == f"video:{CASES / 'clips' / 'run.mp4'}"
    assert config.machine("myagv").source == "camera:0"
    tls = load_fleet(CASES / "valid-multi-host-tls.yaml")
    assert tls.zenoh.tls.root_ca == str(CASES / "certs" / "ca.pem")
    assert tls.db_path == Path("/var/lib/elasticfog/field.sqlite")


def test_fogros_shorthand_and_per_robot_initial_policy() -> None:
    config = load_fleet(CASES / "valid-fogros-shorthand.yaml")
    assert config.latency_bound.stat == "p95"
    assert config.latency_bound.seconds == 0.2
    assert config.latency_bound.window == 50
    assert config.initial_service("turtlebot") == "edge"
    assert config.initial_service("myagv") == "cloud"
    assert config.initial_state("cloud", "turtlebot") == "standby"
    assert config.robot_ids == ["turtlebot", "myagv"]
    assert config.deployment_ids == ["edge", "cloud"]


def test_machine_lookup_lists_known_ids() -> None:
    config = load_fleet(CASES / "valid-single-host.yaml")
    assert config.machine("edge-2").role == "cloud"
    assert config.machine("robot-1", role="robot").fps == 10
    with pytest.raises(UserError) as info:
        config.machine("edge-9")
    assert "no machine 'edge-9'" in str(info.value)
    assert "known machines: edge-1, edge-2, robot-1" in str(info.value)
    assert "valid-single-host.yaml" in str(info.value)
    with pytest.raises(UserError, match=r"'robot-1' is a robot machine .* not a cloud"):
        config.machine("robot-1", role="cloud")


def test_the_deployments_that_admit_fewer_than_a_robot_keeps_in_flight() -> None:
    data = yaml.safe_load((CASES / "valid-single-host.yaml").read_text())
    data["machines"]["edge-2"]["batching"] = {"max_in_flight_per_robot": 3}
    anycast = fleet_from_dict(data)
    assert anycast.short_of_in_flight(3) == {}, "a cap of 3 on edge-2, the default 8 on edge-1"
    assert anycast.short_of_in_flight(4) == {"edge-2": 3}
    assert anycast.short_of_in_flight(9) == {"edge-1": 8, "edge-2": 3}
    pooled = fleet_from_dict({**data, "dispatch": "round_robin"})
    assert pooled.short_of_in_flight(6) == {}, "three frames for each of the two members"
    assert pooled.short_of_in_flight(7) == {"edge-2": 3}


def test_in_memory_config_without_a_file() -> None:
    data = yaml.safe_load((CASES / "valid-minimal.yaml").read_text())
    config = fleet_from_dict(data)
    assert config.source_path is None
    with pytest.raises(UserError, match=r"^fleet config: deadline_s"):
        fleet_from_dict({**data, "deadline_s": 0})


def test_several_errors_stay_on_one_line() -> None:
    with pytest.raises(UserError) as info:
        fleet_from_dict({"service": "v", "model": "zoo:vgg", "a": 1, "b": 2}, source="f.yaml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("f.yaml: ")
    for words in ("a: unknown key", "b: unknown key", "latency_bound: required key is missing"):
        assert words in message


def _models() -> list[type[BaseModel]]:
    """Every pydantic model defined in common.config."""
    found = []
    for value in vars(config_module).values():
        is_model = isinstance(value, type) and issubclass(value, BaseModel)
        if is_model and value.__module__ == config_module.__name__ and value.model_fields:
            found.append(value)
    return found


def test_every_field_has_a_description() -> None:
    models = _models()
    assert FleetConfig in models and len(models) >= 9
    for model in models:
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no description"


def test_every_model_forbids_unknown_keys() -> None:
    for model in _models():
        assert model.model_config.get("extra") == "forbid", model.__name__


def test_latency_stats_are_the_documented_ones() -> None:
    assert typing.get_args(config_module.LatencyStat) == ("median", "mean", "p95", "max", "stddev")


def test_initial_states_are_the_wire_enum() -> None:
    """Guards against initial states compared as strings beside the wire's DeploymentState: a
    cloud's state at start is read into the enum where the file is read, and draining (a state on
    the wire, but none to start in) is refused there."""
    config = load_fleet(CASES / "valid-fogros-shorthand.yaml")
    states = {config.initial_state(d, r) for d in config.deployment_ids for r in config.robot_ids}
    assert states == {DeploymentState.SERVICE, DeploymentState.STANDBY}
    data = yaml.safe_load((CASES / "valid-single-host.yaml").read_text())
    with pytest.raises(UserError, match="'draining' is not a state; expected one of robot, "):
        fleet_from_dict(
            {**data, "initial_policy": {**data["initial_policy"], "edge-2": "draining"}}
        )
