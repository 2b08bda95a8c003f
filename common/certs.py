"""The fleet's certificates: a fleet CA, one certificate and key per host, and the checks a daemon
runs on its TLS files before it opens a session.

Made with the `cryptography` library only (no openssl shell-outs), so `elasticfog certs` works on
any host that runs the daemons. The layout is a contract (docs/security.md):

    DIR/ca.crt            the fleet CA's certificate (PEM), copied to every host
    DIR/ca.key            the CA's private key (0600): keep it off the hosts, it signs new certs
    DIR/<host>.crt        a host's certificate, common name = its machine id (PEM, 0644)
    DIR/<host>.key        its private key (0600)

A folder DIR that does not exist yet is created 0700 (it holds private keys); one that exists
keeps its mode (it may be the user's own folder). Modes are set explicitly, whatever the umask,
so the start checks (`common.tls_preflight`) accept what `elasticfog certs` writes.

Keys are ECDSA P-256 in PKCS#8 (what rustls, under Zenoh's TLS links, reads). A host certificate
is for both ends of a link (server and client auth): peers accept connections and make them.
Its SANs are 127.0.0.1 and localhost unless told otherwise, plus the `--ip`/`--dns` names given
for it; Zenoh checks the name of the endpoint it connects to against them.

Why the checks (`check_tls_files`, `check_san`): Zenoh logs a WARN and retries forever when a
certificate is wrong, so a daemon with a bad file would sit there looking alive. Each problem —
missing file, unreadable PEM, key not matching the certificate, certificate not signed by the
CA, expired or not yet valid, a name missing from the SANs — is one `CertError` line naming the
file and the reason, and the CLI exits 2.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from common.errors import UserError
from common.keys import validate_id

CA_NAME = "ca"
CLI_HOST = "cli"
CERT_SUFFIX = ".crt"
KEY_SUFFIX = ".key"
DEFAULT_DAYS = 365
CA_DAYS_MARGIN = 1
"""The CA outlives the certificates it signs by this many days (a host cert never outlives it)."""
DEFAULT_IPS = ("127.0.0.1",)
DEFAULT_DNS = ("localhost",)
KEY_MODE = 0o600
CERT_MODE = 0o644
"""Certificates are public (every host has the CA's), but only their owner may change them."""
DIR_MODE = 0o700
"""A certificate folder created here: owner only, since it holds private keys."""
CLOCK_SKEW_S = 300
"""Certificates start this long before now: hosts whose clocks differ a little still agree."""
CA_COMMON_NAME_PREFIX = "elasticfog fleet CA"


PrivateKey = Any  # one of cryptography's private key types (a union too wide to spell out)


class CertError(UserError):
    """A certificate or key file that cannot be used; the message names the file and why."""


@dataclass(frozen=True)
class CertInfo:
    """What `certs show` prints about one certificate."""

    host: str
    path: Path
    common_name: str
    not_before: dt.datetime
    not_after: dt.datetime
    ips: tuple[str, ...] = ()
    dns: tuple[str, ...] = ()
    is_ca: bool = False

    def to_json(self) -> dict[str, object]:
        return {
            "host": self.host,
            "path": str(self.path),
            "common_name": self.common_name,
            "not_before": self.not_before.isoformat(),
            "not_after": self.not_after.isoformat(),
            "ips": list(self.ips),
            "dns": list(self.dns),
            "ca": self.is_ca,
        }


@dataclass(frozen=True)
class SanSpec:
    """The names one host's certificate carries (defaults: 127.0.0.1 and localhost)."""

    ips: tuple[str, ...] = DEFAULT_IPS
    dns: tuple[str, ...] = DEFAULT_DNS
    extra_ips: tuple[str, ...] = field(default=())
    extra_dns: tuple[str, ...] = field(default=())

    def all_ips(self) -> list[str]:
        return list(dict.fromkeys([*self.ips, *self.extra_ips]))

    def all_dns(self) -> list[str]:
        return list(dict.fromkeys([*self.dns, *self.extra_dns]))


# -- paths -----------------------------------------------------------------------------------------
def cert_path(directory: Path, host: str) -> Path:
    """`DIR/<host>.crt`."""
    return Path(directory) / f"{host}{CERT_SUFFIX}"


def key_path(directory: Path, host: str) -> Path:
    """`DIR/<host>.key`."""
    return Path(directory) / f"{host}{KEY_SUFFIX}"


def ca_cert_path(directory: Path) -> Path:
    """`DIR/ca.crt`."""
    return cert_path(directory, CA_NAME)


def ca_key_path(directory: Path) -> Path:
    """`DIR/ca.key`."""
    return key_path(directory, CA_NAME)


def _check_host(host: str) -> str:
    validate_id(host, "host")
    if host == CA_NAME:
        raise CertError(f"host {host!r}: the name is taken by the CA's own files (ca.crt, ca.key)")
    return host


# -- options ---------------------------------------------------------------------------------------
def parse_host_values(values: Sequence[str], option: str) -> dict[str, list[str]]:
    """`--ip HOST=ADDR` / `--dns HOST=NAME` options as host -> values; CertError on a bad one."""
    out: dict[str, list[str]] = {}
    for value in values:
        host, sep, name = value.partition("=")
        if not sep or not host or not name:
            raise CertError(f"{option} {value!r}: expected HOST=VALUE, e.g. edge-1=10.0.0.5")
        validate_id(host, f"{option} host")
        if option == "--ip":
            try:
                name = str(ipaddress.ip_address(name))
            except ValueError:
                raise CertError(f"{option} {value!r}: {name!r} is not an IP address") from None
        out.setdefault(host, []).append(name)
    return out


# -- making certificates ---------------------------------------------------------------------------
def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def make_cert_dir(directory: Path) -> None:
    """Create the certificate folder 0700 (its parents as usual); an existing one is left as it
    is. Only the owner may list it or add files: it holds private keys."""
    directory = Path(directory)
    if directory.is_dir():
        return
    try:
        directory.parent.mkdir(parents=True, exist_ok=True)
        directory.mkdir(mode=DIR_MODE)
        os.chmod(directory, DIR_MODE)  # mkdir's mode went through the umask
    except FileExistsError:
        if not directory.is_dir():
            raise CertError(
                f"{directory}: cannot create the folder: a file is in the way"
            ) from None
    except OSError as exc:
        raise CertError(f"{directory}: cannot create the folder: {exc.strerror or exc}") from None


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write `data` with exactly `mode`: set on the open file before a byte is written, so an
    existing file of a wider mode (O_CREAT keeps it) never holds the new content, and the umask
    cannot narrow a certificate's mode either."""
    make_cert_dir(path.parent)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "wb") as out:
            os.fchmod(out.fileno(), mode)
            out.write(data)
    except OSError as exc:
        raise CertError(f"{path}: cannot write: {exc.strerror or exc}") from None


def _write_private(path: Path, data: bytes) -> None:
    """A private key: readable by its owner only (0600)."""
    _write(path, data, KEY_MODE)


def _write_public(path: Path, data: bytes) -> None:
    """A certificate: readable by all, writable by its owner (0644)."""
    _write(path, data, CERT_MODE)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def make_ca(
    directory: Path, *, fleet: str = "", days: int = DEFAULT_DAYS, force: bool = False
) -> Path:
    """Write DIR/ca.crt and DIR/ca.key (a new fleet CA); CertError if they exist and not force."""
    crt, key_file = ca_cert_path(directory), ca_key_path(directory)
    if not force and (crt.exists() or key_file.exists()):
        raise CertError(f"{crt}: a CA exists already; use --force to replace it (and every cert)")
    if days < 1:
        raise CertError(f"--days {days}: expected at least 1")
    key = _new_key()
    name = x509.Name(
        [x509.NameAttribute(NameOID.COMMON_NAME, f"{CA_COMMON_NAME_PREFIX} {fleet}".strip())]
    )
    start = _now() - dt.timedelta(seconds=CLOCK_SKEW_S)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days + CA_DAYS_MARGIN))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_private(key_file, _key_pem(key))
    _write_public(crt, _cert_pem(cert))
    return crt


def load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """The CA of DIR (certificate and key); CertError naming the file when one is missing/bad."""
    cert = load_cert(ca_cert_path(directory))
    key = load_key(ca_key_path(directory))
    if not _same_public_key(cert, key):
        raise CertError(f"{ca_key_path(directory)}: does not match {ca_cert_path(directory)}")
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{ca_key_path(directory)}: expected an ECDSA key")
    return cert, key


def issue(
    directory: Path,
    host: str,
    *,
    sans: SanSpec | None = None,
    days: int = DEFAULT_DAYS,
    force: bool = False,
    not_before: dt.datetime | None = None,
    not_after: dt.datetime | None = None,
) -> tuple[Path, Path]:
    """Sign a certificate for `host` with DIR's CA: DIR/<host>.crt and DIR/<host>.key (0600).

    `not_before`/`not_after` override the validity (tests make expired certificates with them).
    """
    _check_host(host)
    crt, key_file = cert_path(directory, host), key_path(directory, host)
    if not force and (crt.exists() or key_file.exists()):
        raise CertError(f"{crt}: exists already; use --force to replace it")
    if days < 1:
        raise CertError(f"--days {days}: expected at least 1")
    ca_cert, ca_key = load_ca(directory)
    sans = sans or SanSpec()
    names: list[x509.GeneralName] = [x509.DNSName(n) for n in sans.all_dns()]
    names += [x509.IPAddress(ipaddress.ip_address(a)) for a in sans.all_ips()]
    if not names:
        raise CertError(f"host {host!r}: a certificate needs at least one IP or DNS name")
    start = not_before or (_now() - dt.timedelta(seconds=CLOCK_SKEW_S))
    end = not_after or min(start + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    key = _new_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, host)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        # Every host is a server (it listens) and a client (it connects) of a TLS link.
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    _write_private(key_file, _key_pem(key))
    _write_public(crt, _cert_pem(cert))
    return crt, key_file


def init_fleet_certs(
    directory: Path,
    hosts: Iterable[str],
    *,
    ips: Mapping[str, Sequence[str]] | None = None,
    dns: Mapping[str, Sequence[str]] | None = None,
    days: int = DEFAULT_DAYS,
    fleet: str = "",
    force: bool = False,
) -> list[Path]:
    """A new CA and one certificate per host, plus the read-only `cli` one. Returns the
    certificate paths (CA first)."""
    wanted = list(dict.fromkeys([*(_check_host(h) for h in hosts), CLI_HOST]))
    ips, dns = dict(ips or {}), dict(dns or {})
    unknown = sorted((set(ips) | set(dns)) - set(wanted))
    if unknown:
        raise CertError(
            f"--ip/--dns name host(s) not in --hosts: {', '.join(unknown)} "
            f"(hosts: {', '.join(wanted)})"
        )
    if not force:
        for host in [CA_NAME, *wanted]:
            for path in (cert_path(directory, host), key_path(directory, host)):
                if path.exists():
                    raise CertError(f"{path}: exists already; use --force to replace it")
    made = [make_ca(directory, fleet=fleet, days=days, force=True)]
    for host in wanted:
        sans = SanSpec(extra_ips=tuple(ips.get(host, ())), extra_dns=tuple(dns.get(host, ())))
        made.append(issue(directory, host, sans=sans, days=days, force=True)[0])
    return made


# -- reading ---------------------------------------------------------------------------------------
def _read(path: Path, what: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise CertError(f"{path}: no such file ({what})") from None
    except IsADirectoryError:
        raise CertError(f"{path}: is a directory, expected a PEM {what}") from None
    except OSError as exc:
        raise CertError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None


def load_cert(path: Path) -> x509.Certificate:
    """One PEM certificate; CertError naming the file if it is missing or not a certificate."""
    data = _read(path, "certificate")
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError:
        raise CertError(f"{path}: not a PEM certificate") from None


def load_ca_bundle(path: Path) -> list[x509.Certificate]:
    """Every certificate of a PEM file (a CA bundle); CertError naming the file if none."""
    data = _read(path, "CA certificate")
    try:
        found = x509.load_pem_x509_certificates(data)
    except ValueError:
        found = []
    if not found:
        raise CertError(f"{path}: not a PEM certificate")
    return found


def load_key(path: Path) -> PrivateKey:
    """One unencrypted PEM private key; CertError naming the file if missing or unreadable."""
    data = _read(path, "private key")
    try:
        return serialization.load_pem_private_key(data, password=None)
    except TypeError:
        raise CertError(f"{path}: the private key is encrypted (Zenoh needs it in clear)") from None
    except (ValueError, UnsupportedAlgorithm):
        raise CertError(f"{path}: not a PEM private key") from None


def _same_public_key(cert: x509.Certificate, key: object) -> bool:
    public = getattr(key, "public_key", None)
    if public is None:
        return False
    fmt = serialization.PublicFormat.SubjectPublicKeyInfo
    enc = serialization.Encoding.DER
    return bool(cert.public_key().public_bytes(enc, fmt) == public().public_bytes(enc, fmt))


def common_name(cert: x509.Certificate) -> str:
    """The certificate's subject common name ('' when it has none)."""
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def subject_alt_names(cert: x509.Certificate) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(IP addresses, DNS names) of the certificate's SAN extension."""
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return (), ()
    ips = tuple(str(a) for a in san.get_values_for_type(x509.IPAddress))
    dns = tuple(san.get_values_for_type(x509.DNSName))
    return ips, dns


def _is_ca(cert: x509.Certificate) -> bool:
    try:
        return bool(cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        return False


def info(path: Path, host: str | None = None) -> CertInfo:
    """What a certificate file says (CN, validity, SANs)."""
    cert = load_cert(path)
    ips, dns = subject_alt_names(cert)
    return CertInfo(
        host=host or Path(path).stem,
        path=Path(path),
        common_name=common_name(cert),
        not_before=cert.not_valid_before_utc,
        not_after=cert.not_valid_after_utc,
        ips=ips,
        dns=dns,
        is_ca=_is_ca(cert),
    )


def show(directory: Path) -> list[CertInfo]:
    """Every certificate of DIR (the CA first, then hosts by name); CertError if there is no CA."""
    directory = Path(directory)
    ca = ca_cert_path(directory)
    if not ca.exists():
        raise CertError(f"{ca}: no such file (make one with `elasticfog certs init {directory}`)")
    hosts = sorted(p for p in directory.glob(f"*{CERT_SUFFIX}") if p != ca)
    return [info(ca, CA_NAME), *(info(p) for p in hosts)]


# -- checks before a session opens -----------------------------------------------------------------
def _validity_problem(cert: x509.Certificate, now: dt.datetime) -> str | None:
    if now < cert.not_valid_before_utc:
        return f"not valid yet (valid from {cert.not_valid_before_utc:%Y-%m-%d %H:%M:%S} UTC)"
    if now > cert.not_valid_after_utc:
        return f"expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M:%S} UTC"
    return None


def verify_signed_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    """Whether `ca` signed `cert` (issuer name and signature)."""
    if cert.issuer != ca.subject:
        return False
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def check_tls_files(
    ca: str | Path | None,
    cert: str | Path | None = None,
    key: str | Path | None = None,
    *,
    common_name_expected: str | None = None,
    now: dt.datetime | None = None,
) -> None:
    """Check a session's TLS files before Zenoh reads them; CertError naming the file and why.

    The CA must be a CA certificate in date; the certificate must be in date, signed by that CA
    and match the key; with `common_name_expected`, its common name must be that machine id (the
    access control knows a host by it)."""
    now = now or _now()
    cas: list[x509.Certificate] = []
    if ca is not None:
        # A bundle of several CAs is how a CA is rotated (old and new trusted for a while).
        cas = load_ca_bundle(Path(ca))
        for ca_cert in cas:
            if not _is_ca(ca_cert):
                raise CertError(
                    f"{ca}: not a CA certificate (basic constraints CA:FALSE or missing)"
                )
        problems = [_validity_problem(c, now) for c in cas]
        if all(problems):
            raise CertError(f"{ca}: the CA certificate is {problems[0]}")
    if cert is None or key is None:
        return
    host_cert = load_cert(Path(cert))
    host_key = load_key(Path(key))
    if not _same_public_key(host_cert, host_key):
        raise CertError(f"{key}: this private key does not match the certificate {cert}")
    problem = _validity_problem(host_cert, now)
    if problem:
        raise CertError(f"{cert}: the certificate is {problem}")
    if cas and not any(verify_signed_by(host_cert, c) for c in cas):
        raise CertError(
            f"{cert}: not signed by the fleet CA {ca} (issuer: {host_cert.issuer.rfc4514_string()})"
        )
    if common_name_expected is not None and common_name(host_cert) != common_name_expected:
        raise CertError(
            f"{cert}: common name is {common_name(host_cert)!r}, expected the machine id "
            f"{common_name_expected!r} (the access control knows a host by it)"
        )


def _covers(cert: x509.Certificate, host: str) -> bool:
    ips, dns = subject_alt_names(cert)
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        wanted = host.lower().rstrip(".")
        for name in dns:
            name = name.lower().rstrip(".")
            if name == wanted:
                return True
            if name.startswith("*.") and wanted.split(".", 1)[-1] == name[2:]:
                return True
        return False
    return str(address) in {str(ipaddress.ip_address(i)) for i in ips}


UNSPECIFIED_HOSTS = frozenset({"0.0.0.0", "::", "[::]"})


def check_san(cert: str | Path, host: str, why: str) -> None:
    """CertError unless the certificate's SANs carry `host` (an IP or DNS name); `why` says where
    the name comes from. Unspecified listen addresses (0.0.0.0, ::) are not names: skipped."""
    host = host.strip("[]")
    if host in UNSPECIFIED_HOSTS:
        return
    certificate = load_cert(Path(cert))
    if not _covers(certificate, host):
        ips, dns = subject_alt_names(certificate)
        have = ", ".join([*ips, *dns]) or "none"
        raise CertError(
            f"{cert}: no SAN for {host} ({why}); the certificate has {have} "
            f"(add one with `elasticfog certs add HOST --ip/--dns`)"
        )
