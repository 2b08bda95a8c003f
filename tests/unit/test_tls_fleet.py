"""A TLS fleet's configuration: `elasticfog init --tls [--robots N]` writes one that loads with a
certificate per host, each session gets its own host's files (the views CLI its `cli` ones),
`root_ca` still names the CA, and mutual TLS is on unless turned off."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh
from typer.testing import CliRunner

from common.certs import info
from common.cli import app
from common.config import fleet_from_dict, load_fleet
from common.errors import UserError
from common.session import zenoh_config

runner = CliRunner()


def read(conf: zenoh.Config, key: str) -> Any:
    return json.loads(conf.get_json(key))


def test_init_tls_writes_a_ready_fleet(tmp_path: Path) -> None:
    result = runner.invoke(app, ["init", str(tmp_path), "--tls", "--robots", "3", "--port", "7601"])
    assert result.exit_code == 0, result.output
    cfg = load_fleet(tmp_path / "fleet.yaml")
    assert cfg.robot_ids == ["robot-1", "robot-2", "robot-3"]
    assert all(cfg.initial_service(r) == "edge-1" for r in cfg.robot_ids)
    assert cfg.registry.endpoint == "tls/127.0.0.1:7601"
    assert cfg.tls and cfg.mtls and cfg.access_control
    for machine in cfg.machines.values():
        assert machine.listen == ["tls/127.0.0.1:0"]
    certs = tmp_path / "certs"
    for host in ["registry", "edge-1", "edge-2", "robot-1", "robot-2", "robot-3", "cli"]:
        tls = cfg.tls_for(host)
        assert tls.ca == str(certs / "ca.crt")
        assert tls.cert == str(certs / f"{host}.crt") and tls.key == str(certs / f"{host}.key")
        cert = info(Path(tls.cert))
        assert cert.common_name == host and "127.0.0.1" in cert.ips and "localhost" in cert.dns
    # No plaintext endpoint anywhere in the file.
    assert "tcp/" not in (tmp_path / "fleet.yaml").read_text()


def test_init_robots_without_tls(tmp_path: Path) -> None:
    result = runner.invoke(app, ["init", str(tmp_path), "--robots", "2"])
    assert result.exit_code == 0, result.output
    cfg = load_fleet(tmp_path / "fleet.yaml")
    assert cfg.robot_ids == ["robot-1", "robot-2"]
    assert not cfg.tls and not (tmp_path / "certs").exists()
    result = runner.invoke(app, ["init", str(tmp_path / "x"), "--robots", "0"])
    assert result.exit_code == 2 and "--robots 0" in result.output


def test_init_tls_refuses_to_overwrite_certificates(tmp_path: Path) -> None:
    assert runner.invoke(app, ["init", str(tmp_path), "--tls"]).exit_code == 0
    (tmp_path / "fleet.yaml").unlink()
    result = runner.invoke(app, ["init", str(tmp_path), "--tls"])
    assert result.exit_code == 2 and "exists already; use --force" in result.output
    assert runner.invoke(app, ["init", str(tmp_path), "--tls", "--force"]).exit_code == 0


@pytest.fixture(scope="module")
def tls_fleet(tmp_path_factory: pytest.TempPathFactory) -> Any:
    directory = tmp_path_factory.mktemp("tls")
    assert runner.invoke(app, ["init", str(directory), "--tls"]).exit_code == 0
    return load_fleet(directory / "fleet.yaml")


@pytest.mark.parametrize(
    ("kwargs", "host"),
    [
        ({"machine": "robot-1"}, "robot-1"),
        ({"machine": "edge-2"}, "edge-2"),
        ({"router": True}, "registry"),
        ({"identity": "cli", "mode": "client"}, "cli"),
    ],
)
def test_each_session_shows_its_own_certificate(
    tls_fleet: Any, kwargs: dict[str, Any], host: str
) -> None:
    conf = zenoh_config(tls_fleet, **kwargs)
    certs = Path(tls_fleet.source_path).parent / "certs"
    assert read(conf, "transport/link/tls/root_ca_certificate") == str(certs / "ca.crt")
    for side in ("listen", "connect"):
        assert read(conf, f"transport/link/tls/{side}_certificate") == str(certs / f"{host}.crt")
        assert read(conf, f"transport/link/tls/{side}_private_key") == str(certs / f"{host}.key")
    assert read(conf, "transport/link/tls/enable_mtls") is True
    assert read(conf, "access_control/enabled") is True


BASE: dict[str, Any] = {
    "service": "vision",
    "model": "zoo:vgg",
    "deadline_s": 0.5,
    "latency_bound": {"seconds": 0.3},
}


def test_root_ca_is_an_alias_of_ca_and_mtls_defaults_on(tmp_path: Path) -> None:
    cfg = fleet_from_dict(
        {**BASE, "zenoh": {"tls": {"root_ca": "ca.pem", "cert": "h.pem", "key": "h.key"}}},
        source=tmp_path / "fleet.yaml",
    )
    assert cfg.zenoh.tls.ca == cfg.zenoh.tls.root_ca == str(tmp_path / "ca.pem")
    assert cfg.mtls
    # One certificate shared by every host cannot tell hosts apart: no access control then.
    assert not cfg.access_control
    off = fleet_from_dict(
        {**BASE, "zenoh": {"tls": {"ca": "ca.pem", "cert": "h.pem", "key": "h.key", "mtls": False}}}
    )
    assert off.tls and not off.mtls
    assert read(zenoh_config(off), "transport/link/tls/enable_mtls") in (None, False)


def test_shared_certificate_with_access_control_is_refused() -> None:
    data = {
        **BASE,
        "zenoh": {
            "tls": {"ca": "ca.pem", "cert": "h.pem", "key": "h.key"},
            "access_control": True,
        },
    }
    with pytest.raises(UserError, match="needs a certificate per host"):
        fleet_from_dict(data)
