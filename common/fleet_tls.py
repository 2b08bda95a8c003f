"""The TLS part of a fleet: its certificates and the fleet.yaml settings that point at them.

One definition for every fleet this project writes with TLS on (`elasticfog init --tls`, hence
`elasticfog demo --tls`, and the namespace testbed's `elasticfog bench ... --tls`): a fleet CA and
one certificate per host in `certs/` beside the fleet file (`common.certs`, with the read-only
`cli` one), each host's `tls: {cert, key}`, `zenoh.tls: {ca, mtls: true}` and the access control
generated from the file (`common.acl`). Paths are relative to the fleet file, so the folder can
be moved as a whole.

A certificate must carry every address its host listens on (Zenoh checks the name it connects to
against the SANs): 127.0.0.1 and localhost always, plus the `ips` given per host.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

CERTS_DIR = "certs"
"""The certificate folder, relative to the fleet file."""


def host_tls(host: str, certs_dir: str = CERTS_DIR) -> dict[str, str]:
    """A host's own `tls` section: `{cert: certs/<host>.crt, key: certs/<host>.key}`."""
    return {"cert": f"{certs_dir}/{host}.crt", "key": f"{certs_dir}/{host}.key"}


def ca_path(certs_dir: str = CERTS_DIR) -> str:
    """The fleet CA's certificate, relative to the fleet file."""
    return f"{certs_dir}/ca.crt"


def tls_settings(
    registry_id: str, machine_ids: Iterable[str], certs_dir: str = CERTS_DIR
) -> dict[str, Any]:
    """What TLS adds to a fleet.yaml mapping (merge it in): every host's certificate, the CA,
    mutual TLS and the access control on."""
    from common.config import CLI_IDENTITY

    return {
        "registry": {"tls": host_tls(registry_id, certs_dir)},
        "machines": {m: {"tls": host_tls(m, certs_dir)} for m in machine_ids},
        "zenoh": {"tls": {"ca": ca_path(certs_dir), "mtls": True}, "access_control": True},
        "cli": {"tls": host_tls(CLI_IDENTITY, certs_dir)},
    }


def write_certs(
    fleet_dir: Path,
    hosts: Sequence[str],
    *,
    fleet: str = "",
    ips: Mapping[str, Sequence[str]] | None = None,
    force: bool = False,
) -> Path:
    """A new CA and a certificate per host (and `cli`) in `fleet_dir/certs/` (created 0700);
    returns that folder. CertError naming the file when one exists and not `force`."""
    from common.certs import init_fleet_certs  # cryptography: loaded where certificates are made

    directory = Path(fleet_dir) / CERTS_DIR
    init_fleet_certs(directory, hosts, ips=ips, fleet=fleet, force=force)
    return directory
