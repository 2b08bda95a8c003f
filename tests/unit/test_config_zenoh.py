"""The Zenoh session factory: fleet.yaml and explicit arguments become the right Zenoh 1.10 config
keys (read back from a real zenoh.Config, so a renamed key fails here, not in a daemon)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common.config import load_fleet
from common.errors import UserError
from common.session import zenoh_config

CASES = Path(__file__).resolve().parents[1] / "config_cases"


def read(conf: zenoh.Config, key: str) -> Any:
    return json.loads(conf.get_json(key))


@pytest.fixture(scope="module")
def single_host() -> Any:
    return load_fleet(CASES / "valid-single-host.yaml")


def test_every_session_gets_scouting_gossip_and_lease(single_host: Any) -> None:
    for kwargs in ({"machine": "edge-1"}, {"machine": "robot-1"}, {"router": True}, {}):
        conf = zenoh_config(single_host, **kwargs)
        assert read(conf, "scouting/multicast/enabled") is False
        assert read(conf, "scouting/gossip/enabled") is True
        assert read(conf, "transport/link/tx/lease") == 1000
        assert read(conf, "transport/link/tx/keep_alive") == 4
        assert read(conf, "transport/shared_memory/enabled") is True


def test_peer_connects_to_the_registry_and_listens_where_its_machine_says(single_host: Any) -> None:
    conf = zenoh_config(single_host, machine="edge-1")
    assert read(conf, "mode") == "peer"
    assert read(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert read(conf, "listen/endpoints") == ["tcp/127.0.0.1:0"]


def test_router_listens_on_the_registry_endpoints(single_host: Any) -> None:
    conf = zenoh_config(single_host, router=True)
    assert read(conf, "mode") == "router"
    assert read(conf, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert read(conf, "connect/endpoints") == []


def test_explicit_arguments_win(single_host: Any) -> None:
    conf = zenoh_config(
        single_host,
        machine="robot-1",
        mode="client",
        connect=["tcp/10.0.0.1:7447"],
        listen=["tcp/127.0.0.1:7000"],
        shared_memory=False,
        lease_ms=300,
        connect_timeout_s=1.5,
    )
    assert read(conf, "mode") == "client"
    assert read(conf, "connect/endpoints") == ["tcp/10.0.0.1:7447"]
    assert read(conf, "listen/endpoints") == ["tcp/127.0.0.1:7000"]
    assert read(conf, "transport/shared_memory/enabled") is False
    assert read(conf, "transport/link/tx/lease") == 300
    assert read(conf, "connect/timeout_ms") == 1500


def test_machine_overrides_and_tls_files() -> None:
    fleet = load_fleet(CASES / "valid-multi-host-tls.yaml")
    conf = zenoh_config(fleet, machine="robot-7")
    assert read(conf, "mode") == "client"
    # The registry endpoint first, then zenoh.connect; duplicates removed.
    assert read(conf, "connect/endpoints") == [
        "tls/registry.example.org:7447",
        "tls/relay.example.org:7447",
    ]
    assert read(conf, "transport/shared_memory/enabled") is False  # the machine's override
    assert read(conf, "transport/link/tx/lease") == 500
    certs = CASES / "certs"
    assert read(conf, "transport/link/tls/root_ca_certificate") == str(certs / "ca.pem")
    assert read(conf, "transport/link/tls/connect_certificate") == str(certs / "robot.pem")
    assert read(conf, "transport/link/tls/connect_private_key") == str(certs / "robot.key")
    assert read(conf, "transport/link/tls/listen_certificate") == str(certs / "robot.pem")
    assert read(conf, "transport/link/tls/enable_mtls") is True
    gpu = zenoh_config(fleet, machine="gpu-1")
    assert read(gpu, "listen/endpoints") == ["tls/10.0.0.5:7448"]
    assert read(gpu, "transport/shared_memory/enabled") is True


def test_without_a_fleet_file() -> None:
    conf = zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"])
    assert read(conf, "mode") == "client"
    assert read(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert read(conf, "scouting/multicast/enabled") is False


def test_bad_arguments(single_host: Any) -> None:
    with pytest.raises(UserError, match="unknown Zenoh mode 'hub'"):
        zenoh_config(mode="hub")
    with pytest.raises(UserError, match="no machine 'nope'"):
        zenoh_config(single_host, machine="nope")
    with pytest.raises(ValueError, match="contradicts"):
        zenoh_config(router=True, mode="peer")
