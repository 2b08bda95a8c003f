"""Permission checks on the files a daemon trusts, made at start: refuse what another local user
could have changed or read.

- `check_private_file(path, what)`: state a daemon keeps (the registry's RIB sqlite file). The
  file and its folder must not be world-writable: anyone on the host could rewrite the routes, or,
  through the folder, plant a `-journal` file that sqlite replays into the database when it opens
  it (a sticky folder such as /tmp does not stop that: the journal is a new file).
- `check_secret_file(path, what)`: a private key. Readable or writable by group or others is
  refused, as ssh refuses an unprotected key.
- `check_trusted_file(path, what)` and `check_trusted_dir(path, what)`: a certificate or the CA
  bundle, and the folder holding them. Group- or world-writable is refused: whoever can write there
  can swap in their own CA or certificate.

Each problem is an `UnsafePermissions` (a UserError: one line naming the file and its mode, exit
code 2). A path that does not exist is not checked here: whoever opens it reports that.
"""

from __future__ import annotations

import stat
from pathlib import Path

from common.errors import UserError

GROUP_OR_WORLD_WRITABLE = stat.S_IWGRP | stat.S_IWOTH
GROUP_OR_WORLD_ACCESS = stat.S_IRWXG | stat.S_IRWXO


class UnsafePermissions(UserError):
    """A file or folder others can change (or, for a key, read); the message names the path, its
    mode and the chmod that fixes it."""


def check_private_file(path: str | Path, what: str) -> None:
    """Refuse `path` (a daemon's own state) if it or its folder is world-writable."""
    path = Path(path)
    _refuse(path, what, stat.S_IWOTH, "world-writable", "o-w")
    _refuse(path.parent, f"the folder of {what}", stat.S_IWOTH, "world-writable", "o-w")


def check_secret_file(path: str | Path, what: str) -> None:
    """Refuse `path` (a private key) if group or others may read, write or run it."""
    _refuse(Path(path), what, GROUP_OR_WORLD_ACCESS, "open to group or others", "go-rwx")


def check_trusted_file(path: str | Path, what: str) -> None:
    """Refuse `path` (a certificate, a CA bundle) if group or others may write it."""
    _refuse(Path(path), what, GROUP_OR_WORLD_WRITABLE, "group- or world-writable", "go-w")


def check_trusted_dir(path: str | Path, what: str) -> None:
    """Refuse the folder `path` (holding certificates and keys) if group or others may write
    in it (they could replace a file there)."""
    _refuse(Path(path), what, GROUP_OR_WORLD_WRITABLE, "group- or world-writable", "go-w")


def mode_text(mode: int) -> str:
    """Permission bits as chmod takes them, e.g. 0644 (setuid/setgid/sticky bits included)."""
    return f"{stat.S_IMODE(mode):04o}"


def _refuse(path: Path, what: str, forbidden: int, problem: str, chmod: str) -> None:
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise UnsafePermissions(
            f"{what} {path}: cannot check its permissions ({exc.strerror})"
        ) from None
    if mode & forbidden:
        raise UnsafePermissions(
            f"{what} {path}: mode {mode_text(mode)} is {problem}; refusing to use it "
            f"(chmod {chmod} {path})"
        )
