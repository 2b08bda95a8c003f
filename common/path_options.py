"""Path options of the commands, resolved against the working directory and checked before
anything starts.

A command that writes its fleet files elsewhere (a bench's or the demo's temporary folder) would
otherwise read `--model rel.onnx` relative to that folder, and fail after the testbed is up.
"""

from __future__ import annotations

from pathlib import Path

from common.defaults import ZOO_PREFIX
from common.errors import UserError


def model_path(model: str, option: str = "--model") -> str:
    """A zoo name as it is; a file's absolute path (relative: to the working directory), which
    must be a file. UserError naming the option otherwise."""
    if model.startswith(ZOO_PREFIX):
        return model
    path = Path(model).expanduser().resolve()
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "no such file"
        raise UserError(f"{option} {model}: {what} ({path}); expected an ONNX file or zoo:NAME")
    return str(path)


def option_dir(path: Path, option: str) -> Path:
    """A folder option as an absolute path (relative: to the working directory); UserError when
    it names a file."""
    resolved = path.expanduser().resolve()
    if resolved.exists() and not resolved.is_dir():
        raise UserError(f"{option} {path}: is a file, expected a folder")
    return resolved
