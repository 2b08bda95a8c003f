"""Naming a model: an ONNX file path or ``zoo:NAME``, resolved to a file and its sha256 digest.

The digest identifies the model between robot and cloud (requests carry it) and keys every cache
entry (exported zoo models, partitions, profiles) under the user cache directory.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import platformdirs

from common.defaults import ZOO_PREFIX
from common.errors import UserError

CACHE_DIR_ENV = "ELASTICFOG_CACHE_DIR"
_DIGEST_CHUNK_BYTES = 1 << 20


@dataclass(frozen=True)
class ModelRef:
    """A resolved model: the ONNX file, its sha256 digest and a short name for tables and logs."""

    path: Path
    digest: str
    name: str
    spec: str


def cache_dir() -> Path:
    """The user cache directory (``ELASTICFOG_CACHE_DIR`` overrides it); created if missing."""
    override = os.environ.get(CACHE_DIR_ENV)
    root = Path(override) if override else Path(platformdirs.user_cache_dir("elasticfog"))
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create cache directory {root}: {exc.strerror}") from None
    return root


def read_cached_json(path: Path) -> Any:
    """A cache entry written by `write_cached_json`, or None if missing or unreadable (a
    broken entry is measured again, never an error)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def write_cached_json(path: Path, data: Any) -> None:
    """Write a cache entry beside its final name and rename it into place, so a concurrent
    reader never sees half of it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=2)
    os.replace(tmp, path)


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes, as hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_DIGEST_CHUNK_BYTES):
            h.update(chunk)
    return h.hexdigest()


def resolve_model(
    spec: str | Path,
    input_shape: tuple[int, ...] | None = None,
    zoo_options: Mapping[str, float] | None = None,
) -> ModelRef:
    """Resolve ``spec`` (an ONNX file or ``zoo:NAME``) to a file on disk and its digest.

    A zoo model is exported once per name, input shape (C, H, W; a leading batch dimension
    of 1 is accepted) and build options into the cache directory and reused afterwards.
    ``zoo_options`` are build options (a fleet's: `FleetConfig.zoo_options`, the stereo camera's
    geometry); a zoo model takes those it knows (`common.zoo.options_for`), a file none. For a
    file, ``input_shape`` is not used here: the partitioner applies it to the model's dynamic
    dimensions.
    """
    text = str(spec).strip()
    if not text:
        raise UserError("empty model name: give an ONNX file or zoo:NAME")
    if text.startswith(ZOO_PREFIX):
        return _resolve_zoo(text, text[len(ZOO_PREFIX) :], input_shape, zoo_options)
    path = Path(text).expanduser()
    if not path.exists():
        raise UserError(f"model file not found: {text}")
    if not path.is_file():
        raise UserError(f"model path is not a file: {text}")
    return ModelRef(path=path, digest=file_digest(path), name=path.stem, spec=text)


def _resolve_zoo(
    spec: str,
    name: str,
    input_shape: tuple[int, ...] | None,
    options: Mapping[str, float] | None,
) -> ModelRef:
    from common import zoo  # light: the graph builder (numpy, onnx) loads when a model is built

    entry = zoo.get(name)
    shape = zoo_shape(input_shape)
    # The zoo's format is in the file name: a cache filled by an older build (float input
    # before the camera image entered the model) is not mistaken for today's models; so are
    # the build options off their defaults: two camera geometries never share a file.
    path = cache_dir() / "zoo" / zoo.cache_file_name(entry, shape, options)
    if not path.is_file():
        zoo.export(entry.name, path, shape, options)
    return ModelRef(path=path, digest=file_digest(path), name=entry.name, spec=spec)


def zoo_shape(input_shape: tuple[int, ...] | None) -> tuple[int, int, int]:
    """A zoo input shape as (C, H, W): the default, or the given one without its batch of 1."""
    from common import zoo

    if input_shape is None:
        return zoo.DEFAULT_INPUT_SHAPE
    shape = tuple(int(d) for d in input_shape)
    if len(shape) == 4 and shape[0] == 1:
        shape = shape[1:]
    return zoo.check_input_shape(shape)
