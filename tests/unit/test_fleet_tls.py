"""The TLS part of the fleets this project writes (`common.fleet_tls`): the namespace testbed's
fleet with `--tls` (no root, no testbed: its addresses are given) has `tls/` endpoints only, each
host's certificate and key, mutual TLS and the access control, and certificates that pass the
checks every daemon runs at start for the testbed address it listens on; `elasticfog init --tls`
writes the same settings, so the two cannot drift apart."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from common import certs
from common.config import FleetConfig
from common.fleet_tls import tls_settings
from common.init_cli import CLOUD_IDS, render_fleet, robot_ids
from common.session import zenoh_settings
from common.tls_preflight import check_session
from experiments.fleet import FleetSpec, cert_ips, write_fleet

ADDRESSES = {
    "registry": "10.77.0.1",
    "robot": "10.77.0.2",
    "edge-1": "10.77.0.3",
    "edge-2": "10.77.0.4",
    "bench": "10.77.0.5",
}
HOSTS = ("registry", "edge-1", "edge-2", "robot-1")
OBSERVER_LISTEN = "tls/10.77.0.5:7449"


@pytest.fixture(scope="module")
def testbed_fleet(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, FleetConfig]:
    directory = tmp_path_factory.mktemp("run1")
    spec = FleetSpec(fleet="t1", clouds=("edge-1", "edge-2"), serving="edge-1")
    path, cfg = write_fleet(spec, ADDRESSES, directory, tls=True)
    return path, cfg


def test_testbed_fleet_with_tls_has_tls_endpoints_only(
    testbed_fleet: tuple[Path, FleetConfig],
) -> None:
    _, cfg = testbed_fleet
    assert cfg.registry.endpoint == "tls/10.77.0.1:7447"
    assert cfg.registry.listen == ["tls/10.77.0.1:7447"]
    assert cfg.machines["edge-1"].listen == ["tls/10.77.0.3:7448"]
    assert cfg.machines["edge-2"].listen == ["tls/10.77.0.4:7448"]
    assert cfg.machines["robot-1"].listen == ["tls/10.77.0.2:7448"]
    assert cfg.tls and cfg.mtls and cfg.access_control
    assert cfg.zenoh.shared_memory is False  # still the testbed's fleet


def test_testbed_fleet_with_tls_points_at_each_hosts_certificate(
    testbed_fleet: tuple[Path, FleetConfig],
) -> None:
    path, cfg = testbed_fleet
    folder = path.parent / "certs"
    for host in [*HOSTS, "cli"]:
        tls = cfg.tls_for(host)
        assert (tls.ca, tls.cert, tls.key) == (
            str(folder / "ca.crt"),
            str(folder / f"{host}.crt"),
            str(folder / f"{host}.key"),
        )
        assert Path(tls.cert).is_file() and Path(tls.key).is_file()
    # The file names them relative to itself, as `elasticfog init --tls` does.
    data = yaml.safe_load(path.read_text())
    assert data["machines"]["robot-1"]["tls"] == {
        "cert": "certs/robot-1.crt",
        "key": "certs/robot-1.key",
    }
    robot = zenoh_settings(cfg, machine="robot-1")
    assert robot["connect/endpoints"] == ["tls/10.77.0.1:7447"]
    assert robot["transport/link/tls/connect_certificate"] == str(folder / "robot-1.crt")
    assert robot["transport/link/tls/enable_mtls"] is True
    assert robot["access_control"]["default_permission"] == "deny"


def test_testbed_certificates_carry_the_namespace_addresses(
    testbed_fleet: tuple[Path, FleetConfig],
) -> None:
    path, cfg = testbed_fleet
    folder = path.parent / "certs"
    ips = {host: certs.info(folder / f"{host}.crt").ips for host in HOSTS}
    assert "10.77.0.1" in ips["registry"] and "10.77.0.5" in ips["registry"]  # + the observer
    assert "10.77.0.3" in ips["edge-1"] and "10.77.0.4" in ips["edge-2"]
    assert "10.77.0.2" in ips["robot-1"]
    assert cert_ips(FleetSpec(fleet="x"), ADDRESSES)["edge-1"] == ["10.77.0.3"]
    # What each daemon checks at start (files, modes, common name, a SAN for where it listens),
    # short of the handshake with the registry; the registry as the router, the observer with
    # the registry's certificate on the bench host.
    for host in HOSTS[1:]:
        check_session(cfg, host, listen=cfg.machines[host].listen, connect=[])
    check_session(cfg, "registry", listen=cfg.registry.listen, connect=[], router=True)
    check_session(cfg, "registry", listen=[OBSERVER_LISTEN], connect=[])


def test_testbed_fleet_without_tls_stays_plain(tmp_path: Path) -> None:
    path, cfg = write_fleet(FleetSpec(fleet="t2"), ADDRESSES, tmp_path)
    assert cfg.registry.endpoint == "tcp/10.77.0.1:7447" and not cfg.tls
    assert not (path.parent / "certs").exists()


def _contains(data: Any, part: Any) -> bool:
    if isinstance(part, dict):
        return isinstance(data, dict) and all(
            k in data and _contains(data[k], v) for k, v in part.items()
        )
    return bool(data == part)


def test_init_tls_writes_the_same_settings_as_the_testbed() -> None:
    """`elasticfog init --tls` renders its commented template; its TLS settings are
    `tls_settings`', which the testbed merges in, so both secure a fleet the same way."""
    data = yaml.safe_load(render_fleet(robots=2, tls=True))
    expected = tls_settings("registry", [*CLOUD_IDS, *robot_ids(2)])
    assert _contains(data, expected), (data, expected)
    assert all(e.startswith("tls/") for m in data["machines"].values() for e in m["listen"])
