"""`common.certs` and `elasticfog certs`: the fleet CA and host certificates (names, SANs, key
modes are a contract), and every reason a TLS file cannot work named with the file and why."""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import stat
from pathlib import Path

import pytest
from cryptography import x509
from typer.testing import CliRunner

from common import certs
from common.certs import CertError, SanSpec, check_san, check_tls_files
from common.cli import app
from common.config import TlsConfig
from common.tls_preflight import check_permissions

HOSTS = ["registry", "edge-1", "edge-2", "robot-1"]
runner = CliRunner()


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("certs")
    certs.init_fleet_certs(
        directory,
        HOSTS,
        ips={"edge-1": ["10.0.0.5"]},
        dns={"registry": ["registry.example.org"]},
        days=30,
        fleet="test",
    )
    return directory


def test_init_writes_the_contract_layout(fleet_dir: Path) -> None:
    names = sorted(p.name for p in fleet_dir.iterdir())
    expected = ["ca.crt", "ca.key"]
    for host in [*HOSTS, "cli"]:  # the read-only CLI certificate comes along
        expected += [f"{host}.crt", f"{host}.key"]
    assert names == sorted(expected)
    for key in fleet_dir.glob("*.key"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("umask", [0o000, 0o022, 0o077])
def test_init_and_add_write_the_folder_0700_certificates_0644_keys_0600(
    tmp_path: Path, umask: int
) -> None:
    """Modes are exact whatever the umask: a permissive one must not widen them (another user
    could swap a certificate or read a key), a strict one must not narrow a certificate."""
    directory = tmp_path / "fleet" / "certs"
    previous = os.umask(umask)
    try:
        result = runner.invoke(app, ["certs", "init", str(directory), "--hosts", "registry"])
        assert result.exit_code == 0, result.output
        result = runner.invoke(app, ["certs", "add", "robot-1", "--dir", str(directory)])
        assert result.exit_code == 0, result.output
    finally:
        os.umask(previous)
    assert _mode(directory) == 0o700
    files = sorted(directory.iterdir())
    assert [p.name for p in files if p.suffix == ".crt"] == [
        "ca.crt",
        "cli.crt",
        "registry.crt",
        "robot-1.crt",
    ]
    for path in files:
        assert _mode(path) == (0o600 if path.suffix == ".key" else 0o644), path
    # What certs writes passes the checks every daemon runs on its TLS files at start.
    check_permissions(
        TlsConfig(
            ca=str(directory / "ca.crt"),
            cert=str(directory / "robot-1.crt"),
            key=str(directory / "robot-1.key"),
        )
    )


def test_rotation_narrows_files_left_too_open_and_keeps_an_existing_folder(
    tmp_path: Path,
) -> None:
    """`certs add --force` over files someone widened writes them back at 0644/0600 before the
    new bytes go in; a folder that existed (the user's own) keeps its mode."""
    tmp_path.chmod(0o750)
    certs.init_fleet_certs(tmp_path, ["robot-1"])
    assert _mode(tmp_path) == 0o750
    crt, key = certs.cert_path(tmp_path, "robot-1"), certs.key_path(tmp_path, "robot-1")
    crt.chmod(0o666)
    key.chmod(0o644)
    result = runner.invoke(app, ["certs", "add", "robot-1", "--dir", str(tmp_path), "--force"])
    assert result.exit_code == 0, result.output
    assert (_mode(crt), _mode(key)) == (0o644, 0o600)


def test_a_file_in_the_way_of_the_folder_is_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "certs"
    blocker.write_text("not a folder")
    with pytest.raises(CertError) as exc:
        certs.init_fleet_certs(blocker, ["robot-1"])
    _one_line(exc, blocker, "a file is in the way")


def test_common_name_is_the_machine_id_and_sans_default_to_loopback(fleet_dir: Path) -> None:
    by_host = {i.host: i for i in certs.show(fleet_dir)}
    assert by_host["ca"].is_ca
    for host in [*HOSTS, "cli"]:
        info = by_host[host]
        assert info.common_name == host
        assert not info.is_ca
        assert "127.0.0.1" in info.ips and "localhost" in info.dns
        assert dt.timedelta(days=29) < info.not_after - info.not_before <= dt.timedelta(days=30)
    assert by_host["edge-1"].ips == ("127.0.0.1", "10.0.0.5")
    assert by_host["registry"].dns == ("localhost", "registry.example.org")
    # The CA outlives what it signs.
    assert all(by_host["ca"].not_after >= i.not_after for i in by_host.values())


def test_host_certificates_serve_and_connect(fleet_dir: Path) -> None:
    cert = certs.load_cert(certs.cert_path(fleet_dir, "robot-1"))
    usage = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert x509.oid.ExtendedKeyUsageOID.SERVER_AUTH in usage
    assert x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH in usage
    assert certs.verify_signed_by(cert, certs.load_cert(certs.ca_cert_path(fleet_dir)))
    check_tls_files(
        fleet_dir / "ca.crt",
        fleet_dir / "robot-1.crt",
        fleet_dir / "robot-1.key",
        common_name_expected="robot-1",
    )


def test_init_refuses_to_overwrite_and_unknown_san_hosts(tmp_path: Path) -> None:
    certs.init_fleet_certs(tmp_path, ["robot-1"])
    with pytest.raises(CertError, match="exists already; use --force"):
        certs.init_fleet_certs(tmp_path, ["robot-1"])
    with pytest.raises(CertError, match="not in --hosts: edge-9"):
        certs.init_fleet_certs(tmp_path, ["robot-1"], ips={"edge-9": ["10.0.0.9"]}, force=True)
    with pytest.raises(CertError, match="taken by the CA"):
        certs.init_fleet_certs(tmp_path, ["ca"], force=True)


@pytest.mark.parametrize(
    ("value", "words"),
    [("edge-1", "expected HOST=VALUE"), ("edge-1=not-an-ip", "is not an IP address")],
)
def test_bad_ip_options(value: str, words: str) -> None:
    with pytest.raises(CertError, match=words):
        certs.parse_host_values([value], "--ip")


# -- every failure: one line naming the file and the reason ----------------------------------------
def _copy(fleet_dir: Path, tmp_path: Path) -> Path:
    target = tmp_path / "certs"
    shutil.copytree(fleet_dir, target)
    return target


def _one_line(exc: pytest.ExceptionInfo[CertError], path: Path, words: str) -> None:
    message = str(exc.value)
    assert "\n" not in message
    assert message.startswith(str(path)), message
    assert words in message, message
    assert exc.value.exit_code == 2


def test_missing_file(fleet_dir: Path, tmp_path: Path) -> None:
    missing = tmp_path / "nope.key"
    with pytest.raises(CertError) as exc:
        check_tls_files(fleet_dir / "ca.crt", fleet_dir / "robot-1.crt", missing)
    _one_line(exc, missing, "no such file (private key)")
    with pytest.raises(CertError) as exc:
        check_tls_files(tmp_path / "ca.crt")
    _one_line(exc, tmp_path / "ca.crt", "no such file (CA certificate)")


def test_not_pem(fleet_dir: Path, tmp_path: Path) -> None:
    junk = tmp_path / "robot-1.crt"
    junk.write_text("not a certificate\n")
    with pytest.raises(CertError) as exc:
        check_tls_files(fleet_dir / "ca.crt", junk, fleet_dir / "robot-1.key")
    _one_line(exc, junk, "not a PEM certificate")


def test_key_does_not_match_the_certificate(fleet_dir: Path) -> None:
    key = fleet_dir / "edge-1.key"
    with pytest.raises(CertError) as exc:
        check_tls_files(fleet_dir / "ca.crt", fleet_dir / "robot-1.crt", key)
    _one_line(exc, key, "does not match the certificate")


def test_unknown_ca(fleet_dir: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    certs.init_fleet_certs(other, ["robot-1"])
    with pytest.raises(CertError) as exc:
        check_tls_files(fleet_dir / "ca.crt", other / "robot-1.crt", other / "robot-1.key")
    _one_line(exc, other / "robot-1.crt", "not signed by the fleet CA")
    with pytest.raises(CertError) as exc:
        check_tls_files(fleet_dir / "robot-1.crt")
    _one_line(exc, fleet_dir / "robot-1.crt", "not a CA certificate")


def test_expired_and_not_yet_valid(fleet_dir: Path, tmp_path: Path) -> None:
    directory = _copy(fleet_dir, tmp_path)
    now = dt.datetime.now(dt.timezone.utc)
    certs.issue(
        directory,
        "old",
        not_before=now - dt.timedelta(days=10),
        not_after=now - dt.timedelta(days=1),
    )
    certs.issue(
        directory,
        "early",
        not_before=now + dt.timedelta(days=1),
        not_after=now + dt.timedelta(days=10),
    )
    ca = directory / "ca.crt"
    with pytest.raises(CertError) as exc:
        check_tls_files(ca, directory / "old.crt", directory / "old.key")
    _one_line(exc, directory / "old.crt", "the certificate is expired on")
    with pytest.raises(CertError) as exc:
        check_tls_files(ca, directory / "early.crt", directory / "early.key")
    _one_line(exc, directory / "early.crt", "the certificate is not valid yet")
    # The CA itself, checked on a date past its end.
    later = now + dt.timedelta(days=400)
    with pytest.raises(CertError) as exc:
        check_tls_files(ca, now=later)
    _one_line(exc, ca, "the CA certificate is expired")


def test_wrong_common_name(fleet_dir: Path) -> None:
    crt = fleet_dir / "robot-1.crt"
    with pytest.raises(CertError) as exc:
        check_tls_files(
            fleet_dir / "ca.crt", crt, fleet_dir / "robot-1.key", common_name_expected="robot-2"
        )
    _one_line(exc, crt, "common name is 'robot-1', expected the machine id 'robot-2'")


def test_wrong_san(fleet_dir: Path) -> None:
    crt = fleet_dir / "robot-1.crt"
    check_san(crt, "127.0.0.1", "listen")
    check_san(crt, "localhost", "listen")
    check_san(crt, "0.0.0.0", "listen")  # not a name: every address of the host
    with pytest.raises(CertError) as exc:
        check_san(crt, "10.0.0.7", "it listens on tls/10.0.0.7:7447")
    _one_line(exc, crt, "no SAN for 10.0.0.7 (it listens on tls/10.0.0.7:7447)")
    with pytest.raises(CertError) as exc:
        check_san(crt, "robot.example.org", "registry.endpoint")
    _one_line(exc, crt, "the certificate has 127.0.0.1, localhost")


def test_add_signs_with_the_existing_ca_and_rotates_with_force(
    fleet_dir: Path, tmp_path: Path
) -> None:
    directory = _copy(fleet_dir, tmp_path)
    crt, _ = certs.issue(directory, "robot-9", sans=SanSpec(extra_ips=("192.0.2.9",)))
    info = certs.info(crt)
    assert info.common_name == "robot-9" and "192.0.2.9" in info.ips
    before = crt.read_bytes()
    with pytest.raises(CertError, match="exists already"):
        certs.issue(directory, "robot-9")
    certs.issue(directory, "robot-9", force=True)
    assert crt.read_bytes() != before
    check_tls_files(directory / "ca.crt", crt, directory / "robot-9.key")


# -- the CLI ---------------------------------------------------------------------------------------
def test_cli_init_add_show(tmp_path: Path) -> None:
    directory = tmp_path / "certs"
    result = runner.invoke(
        app,
        [
            "certs",
            "init",
            str(directory),
            "--hosts",
            "registry,edge-1,robot-1",
            "--ip",
            "edge-1=10.0.0.5",
            "--dns",
            "registry=reg.example.org",
            "--days",
            "10",
        ],
    )
    assert result.exit_code == 0, result.output
    assert (directory / "cli.crt").is_file()
    result = runner.invoke(
        app, ["certs", "add", "robot-2", "--dir", str(directory), "--ip", "10.0.0.8"]
    )
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["certs", "show", "--dir", str(directory), "--json"])
    assert result.exit_code == 0, result.output
    rows = {r["host"]: r for r in json.loads(result.output)}
    assert sorted(rows) == ["ca", "cli", "edge-1", "registry", "robot-1", "robot-2"]
    assert rows["robot-2"]["ips"] == ["127.0.0.1", "10.0.0.8"]
    assert rows["registry"]["dns"] == ["localhost", "reg.example.org"]
    assert rows["edge-1"]["common_name"] == "edge-1"
    result = runner.invoke(app, ["certs", "show", "--dir", str(directory)])
    assert result.exit_code == 0 and "robot-2" in result.output


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["init", "{d}", "--hosts", ","], "--hosts: give at least one host"),
        (["init", "{d}", "--hosts", "a/b"], "host 'a/b' contains '/'"),
        (["init", "{d}", "--hosts", "r", "--ip", "r=nope"], "is not an IP address"),
        (["add", "robot-1", "--dir", "{d}"], "ca.crt: no such file"),
        (["add", "robot-1", "--dir", "{d}", "--ip", "edge-1=10.0.0.1"], "adds robot-1 only"),
        (["show", "--dir", "{d}"], "ca.crt: no such file"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], words: str) -> None:
    argv = ["certs", *(a.format(d=tmp_path / "empty") for a in args)]
    result = runner.invoke(app, argv)
    assert result.exit_code == 2, result.output
    assert words in result.output


def test_certs_help_loads_no_cryptography() -> None:
    """`elasticfog certs --help` builds the whole CLI without importing cryptography (or any
    other heavy library): commands import them where they run."""
    import subprocess
    import sys

    code = (
        "import sys\nfrom common.cli import app\n"
        "try:\n    app(['certs', 'add', '--help'], prog_name='elasticfog')\n"
        "except SystemExit as exc:\n    assert exc.code in (0, None)\n"
        "print(sorted(m for m in ('cryptography', 'pydantic', 'zenoh') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout


def test_a_ca_bundle_trusts_old_and_new_during_rotation(fleet_dir: Path, tmp_path: Path) -> None:
    """CA rotation: ca.crt holds the old and the new CA; hosts of both are accepted."""
    new = tmp_path / "new"
    certs.init_fleet_certs(new, ["robot-1"])
    bundle = tmp_path / "ca-bundle.crt"
    bundle.write_bytes((fleet_dir / "ca.crt").read_bytes() + (new / "ca.crt").read_bytes())
    check_tls_files(bundle, fleet_dir / "robot-1.crt", fleet_dir / "robot-1.key")
    check_tls_files(bundle, new / "robot-1.crt", new / "robot-1.key")
    stranger = tmp_path / "stranger"
    certs.init_fleet_certs(stranger, ["robot-1"])
    with pytest.raises(CertError, match="not signed by the fleet CA"):
        check_tls_files(bundle, stranger / "robot-1.crt", stranger / "robot-1.key")
