"""Checks a TLS session passes before it opens, so a wrong certificate is named within seconds.

Zenoh reports a bad TLS file or an untrusted peer with a WARN in its log and then retries
forever: a daemon would look alive and never join the fleet. So before `zenoh.open`:

1. The permissions (`check_permissions`): no folder holding the CA, the certificate or the key,
   and neither certificate, is group- or world-writable (another local user could swap in their
   own CA), and the key is readable by its owner only.
2. The files (`common.certs.check_tls_files`): each exists and is PEM, the key matches the
   certificate, both the CA and the certificate are in date, the CA signed the certificate and,
   with access control on, its common name is this host's id.
3. The names: the certificate carries the host of each `tls/` endpoint it listens on (peers
   check the name they connect to), and the registry's carries the host of `registry.endpoint`.
4. The registry: one TLS handshake with its endpoint, as Zenoh will make it (this host's CA,
   certificate and the endpoint's name). An unknown CA, an expired or not-yet-valid certificate
   or a name missing from its SANs is reported with the endpoint; so is the registry refusing
   this host's certificate (its TLS alert arrives right after the handshake). Nobody listening
   there is not an error: daemons start before the registry and outlive its restarts.

Every failure is one `CertError` line (exit 2) naming the file (and its mode) or the endpoint and
the reason.
"""

from __future__ import annotations

import logging
import socket
import ssl
from collections.abc import Sequence
from pathlib import Path

from common.certs import CertError, check_san, check_tls_files
from common.config import CLI_IDENTITY, FleetConfig, TlsConfig
from common.file_safety import (
    UnsafePermissions,
    check_secret_file,
    check_trusted_dir,
    check_trusted_file,
)

log = logging.getLogger(__name__)

HANDSHAKE_TIMEOUT_S = 2.0
"""How long the probe handshake may take (a TLS listener answers in milliseconds)."""
VERDICT_WAIT_S = 0.25
"""How long to wait, after the handshake, for the peer's alert refusing our certificate (TLS 1.3
sends the server's verdict on the client's certificate after the handshake completes)."""

# OpenSSL's X509_V_ERR_* codes as a reason a person can act on.
_VERIFY_REASONS = {
    9: "its certificate is not valid yet",
    10: "its certificate has expired",
    18: "its certificate is self-signed, not signed by the fleet CA",
    19: "its certificate is not signed by the fleet CA (unknown CA)",
    20: "its certificate is not signed by the fleet CA (unknown CA)",
    21: "its certificate is not signed by the fleet CA (unknown CA)",
    62: "its certificate does not carry this name in its SANs (wrong SAN)",
    64: "its certificate does not carry this address in its SANs (wrong SAN)",
}


def split_tls_endpoint(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a `tls/HOST:PORT[?...]` endpoint; None for other protocols."""
    protocol, _, address = endpoint.partition("/")
    if protocol != "tls":
        return None
    address = address.split("?", 1)[0].split("#", 1)[0]
    host, _, port = address.rpartition(":")
    return host.strip("[]"), int(port)


def _where(cfg: FleetConfig, identity: str | None) -> str:
    if identity is None:
        return "zenoh.tls"
    if identity == cfg.registry.id:
        return "registry.tls"
    if identity == CLI_IDENTITY:
        return "cli.tls"
    return f"machines.{identity}.tls"


def check_session(
    cfg: FleetConfig,
    identity: str | None,
    *,
    listen: Sequence[str],
    connect: Sequence[str],
    router: bool = False,
) -> None:
    """Everything above for one session of `cfg` (a no-op when the fleet has no TLS)."""
    if not cfg.tls:
        return
    tls = cfg.tls_for(identity)
    source = cfg.source_path or "the fleet config"
    if tls.mtls and tls.cert is None:
        raise CertError(
            f"{source}: mutual TLS is on but {_where(cfg, identity)} has no cert/key "
            f"(make one with `elasticfog certs add {identity or 'HOST'}`)"
        )
    expected = identity if cfg.access_control and identity is not None else None
    check_permissions(tls)
    check_tls_files(tls.ca, tls.cert, tls.key, common_name_expected=expected)
    if tls.cert is not None:
        for endpoint in listen:
            parsed = split_tls_endpoint(endpoint)
            if parsed is not None:
                check_san(tls.cert, parsed[0], f"it listens on {endpoint}")
        if router:
            parsed = split_tls_endpoint(cfg.registry.endpoint)
            if parsed is not None:
                check_san(
                    tls.cert,
                    parsed[0],
                    f"registry.endpoint {cfg.registry.endpoint}, where every host connects",
                )
    for endpoint in connect:
        if split_tls_endpoint(endpoint) is not None:
            probe_endpoint(endpoint, tls)


def check_permissions(tls: TlsConfig) -> None:
    """CertError naming the path and its mode when another local user could have changed one of
    this host's TLS files or their folders, or could read its key (a missing file is left to
    `check_tls_files`, which names it)."""
    files = [p for p in (tls.ca, tls.cert, tls.key) if p is not None]
    try:
        for folder in dict.fromkeys(Path(p).parent for p in files):
            check_trusted_dir(folder, "certificate folder")
        if tls.ca is not None:
            check_trusted_file(tls.ca, "CA certificate")
        if tls.cert is not None:
            check_trusted_file(tls.cert, "certificate")
        if tls.key is not None:
            check_secret_file(tls.key, "private key")
    except UnsafePermissions as exc:
        raise CertError(str(exc)) from None


def probe_endpoint(
    endpoint: str, tls: TlsConfig, *, timeout_s: float = HANDSHAKE_TIMEOUT_S
) -> None:
    """One TLS handshake with `endpoint` as this host; CertError naming the endpoint and the
    reason when certificates stop it. Nothing listening (yet) is not an error."""
    parsed = split_tls_endpoint(endpoint)
    if parsed is None:
        return
    host, port = parsed
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    if tls.ca is not None:
        context.load_verify_locations(cafile=tls.ca)
    if tls.cert is not None and tls.key is not None:
        context.load_cert_chain(tls.cert, tls.key)
    try:
        raw = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        log.info("%s: not reachable yet (%s); Zenoh keeps trying", endpoint, exc)
        return
    try:
        with context.wrap_socket(raw, server_hostname=host) as link:
            _await_verdict(link, endpoint, tls)
    except ssl.SSLCertVerificationError as exc:
        reason = _VERIFY_REASONS.get(exc.verify_code, exc.verify_message)
        raise CertError(f"{endpoint}: {reason} (checked with the CA {tls.ca})") from None
    except ssl.SSLError as exc:
        raise CertError(
            f"{endpoint}: TLS handshake failed: {exc.reason or exc} (is it a tls/ endpoint?)"
        ) from None
    except TimeoutError:
        raise CertError(
            f"{endpoint}: no TLS handshake within {timeout_s:g} s (is it a tls/ endpoint?)"
        ) from None
    except OSError as exc:
        log.info("%s: the connection dropped during the TLS check (%s)", endpoint, exc)
    finally:
        raw.close()


def _await_verdict(link: ssl.SSLSocket, endpoint: str, tls: TlsConfig) -> None:
    """Wait briefly for the peer's alert about our certificate (silence means accepted: a Zenoh
    listener then waits for our first message)."""
    link.settimeout(VERDICT_WAIT_S)
    try:
        link.recv(1)
    except TimeoutError:
        return
    except ssl.SSLError as exc:
        mine = Path(tls.cert) if tls.cert is not None else None
        what = (
            f"this host's certificate {mine}"
            if mine is not None
            else "a host without a certificate"
        )
        raise CertError(
            f"{endpoint}: the peer refused {what}: {exc.reason or exc} "
            "(signed by another CA, or unknown there?)"
        ) from None
