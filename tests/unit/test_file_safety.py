"""Permission checks at start: the registry's RIB file (`check_private_file`: no world-writable
file or folder) and the TLS files (`tls_preflight.check_permissions`: no group- or world-writable
certificate or folder, a key for its owner only), each refusal one line naming the path and its
mode, exit code 2 through the CLI."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from common.certs import CertError
from common.cli import app
from common.config import load_fleet
from common.file_safety import (
    UnsafePermissions,
    check_private_file,
    check_secret_file,
    check_trusted_dir,
    check_trusted_file,
    mode_text,
)
from common.tls_preflight import check_permissions

runner = CliRunner()


def _file(folder: Path, mode: int, folder_mode: int = 0o700) -> Path:
    folder.mkdir(exist_ok=True)
    path = folder / "rib.sqlite"
    path.write_bytes(b"")
    path.chmod(mode)
    folder.chmod(folder_mode)
    return path


def _refused(exc: pytest.ExceptionInfo[Exception], path: Path, mode: str) -> None:
    message = str(exc.value)
    assert str(path) in message and f"mode {mode}" in message and "\n" not in message
    assert getattr(exc.value, "exit_code", None) == 2


# -- the RIB file ----------------------------------------------------------------------------------
@pytest.mark.parametrize(("mode", "folder_mode"), [(0o600, 0o700), (0o660, 0o750), (0o644, 0o755)])
def test_private_file_accepted(tmp_path: Path, mode: int, folder_mode: int) -> None:
    check_private_file(_file(tmp_path / "rib", mode, folder_mode), "RIB file")


def test_private_file_that_does_not_exist_yet_is_fine(tmp_path: Path) -> None:
    """The registry creates its RIB on first start: nothing to check then but the folder."""
    check_private_file(tmp_path / "new.sqlite", "RIB file")


def test_world_writable_rib_file_is_refused(tmp_path: Path) -> None:
    path = _file(tmp_path / "rib", 0o666)
    with pytest.raises(UnsafePermissions, match="world-writable") as exc:
        check_private_file(path, "RIB file")
    _refused(exc, path, "0666")


@pytest.mark.parametrize("folder_mode", [0o777, 0o1777], ids=["plain", "sticky"])
def test_rib_file_in_a_world_writable_folder_is_refused(tmp_path: Path, folder_mode: int) -> None:
    """Sticky or not: another user can still create the `-journal` file sqlite would replay."""
    path = _file(tmp_path / "shared", 0o600, folder_mode)
    with pytest.raises(UnsafePermissions, match="the folder of RIB file") as exc:
        check_private_file(path, "RIB file")
    _refused(exc, path.parent, mode_text(path.parent.stat().st_mode))


# -- keys, certificates, their folder --------------------------------------------------------------
@pytest.mark.parametrize("mode", [0o640, 0o604, 0o620, 0o606, 0o644])
def test_key_open_to_others_is_refused(tmp_path: Path, mode: int) -> None:
    key = _file(tmp_path / "k", mode)
    with pytest.raises(UnsafePermissions, match="open to group or others") as exc:
        check_secret_file(key, "private key")
    _refused(exc, key, f"{mode:04o}")
    key.chmod(0o600)
    check_secret_file(key, "private key")
    key.chmod(0o400)
    check_secret_file(key, "private key")


@pytest.mark.parametrize("mode", [0o664, 0o646, 0o666])
def test_writable_certificate_is_refused(tmp_path: Path, mode: int) -> None:
    cert = _file(tmp_path / "c", mode)
    with pytest.raises(UnsafePermissions, match="group- or world-writable"):
        check_trusted_file(cert, "certificate")
    cert.chmod(0o644)
    check_trusted_file(cert, "certificate")


@pytest.mark.parametrize("mode", [0o775, 0o757, 0o777, 0o1777])
def test_writable_certificate_folder_is_refused(tmp_path: Path, mode: int) -> None:
    folder = tmp_path / "certs"
    folder.mkdir()
    folder.chmod(mode)
    with pytest.raises(UnsafePermissions, match="certificate folder") as exc:
        check_trusted_dir(folder, "certificate folder")
    _refused(exc, folder, f"{mode:04o}")
    folder.chmod(0o755)
    check_trusted_dir(folder, "certificate folder")


# -- the TLS preflight and the CLI -----------------------------------------------------------------
@pytest.fixture
def tls_fleet(tmp_path: Path) -> Path:
    assert runner.invoke(app, ["init", str(tmp_path), "--tls"]).exit_code == 0
    return tmp_path


def test_the_files_init_writes_pass(tls_fleet: Path) -> None:
    cfg = load_fleet(tls_fleet / "fleet.yaml")
    for host in ("registry", "edge-1", "robot-1", "cli"):
        check_permissions(cfg.tls_for(host))


@pytest.mark.parametrize(
    ("target", "mode"),
    [("robot-1.key", 0o644), ("ca.crt", 0o666), ("robot-1.crt", 0o664), (".", 0o777)],
    ids=["key-readable", "ca-writable", "cert-writable", "folder-writable"],
)
def test_preflight_refuses_unsafe_tls_files(tls_fleet: Path, target: str, mode: int) -> None:
    path = (tls_fleet / "certs" / target).resolve()
    os.chmod(path, mode)
    cfg = load_fleet(tls_fleet / "fleet.yaml")
    with pytest.raises(CertError) as exc:
        check_permissions(cfg.tls_for("robot-1"))
    _refused(exc, path, f"{mode:04o}")


def test_cli_exits_2_naming_the_key_and_its_mode(tls_fleet: Path) -> None:
    """The views CLI opens its session with the `cli` certificate: a key others can read stops
    it before any connection, with one line and exit code 2."""
    key = tls_fleet / "certs" / "cli.key"
    key.chmod(0o644)
    result = runner.invoke(app, ["routes", "--config", str(tls_fleet / "fleet.yaml")])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and str(key) in lines[0] and "mode 0644" in lines[0], result.output
