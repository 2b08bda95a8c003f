"""The partition cache: one split directory per model digest and options, under
``<cache>/partitions/``, published whole by renaming a finished temporary directory.

The entry's name and key are a contract with splits already on users' disks: the key's fields
and their values below do not change unless old entries are meant to be made again.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import onnxruntime as ort

from common.errors import UserError
from common.models import ModelRef, cache_dir
from common.partition.manifest import MANIFEST_FORMAT, MANIFEST_NAME, Partition
from common.partition.options import InputShape


def entry_dir(
    ref: ModelRef,
    cuts: str | list[str],
    max_cut_tensors: int,
    input_shape: InputShape,
    verify: bool,
    atol: float,
    prune: bool,
    *,
    segments: bool = False,
) -> Path:
    """Where the split of ``ref`` with these options is kept (whether or not it exists yet)."""
    key_src = json.dumps(
        {
            "format": MANIFEST_FORMAT,
            "digest": ref.digest,
            "cuts": cuts,
            "max_cut_tensors": max_cut_tensors,
            "input_shape": _shape_key(input_shape),
            "verify": verify,
            "atol": atol,
            "prune": prune,
            "onnxruntime": ort.__version__,
            # 2: only initializers no optimization rewrites in place are shared, and verified
            # against onnxruntime's own run; splits cached before are made and checked again.
            "sharing": 2,
            # Only when on, so that the entries of splits without segments keep their names.
            **({"segments": True} if segments else {}),
        },
        sort_keys=True,
    )
    key = hashlib.sha256(key_src.encode()).hexdigest()[:16]
    return cache_dir() / "partitions" / f"{ref.name}-{ref.digest[:12]}-{key}"


def read_entry(final: Path) -> Partition | None:
    """The split cached at ``final`` if its manifest loads and every file it names is there."""
    if not (final / MANIFEST_NAME).is_file():
        return None
    with contextlib.suppress(UserError):
        cached = Partition.load(final)
        if all(p.is_file() for p in cached.files()):
            return cached
    return None


def write_entry(final: Path, make: Callable[[Path], object]) -> Partition:
    """Make the split with ``make(directory)`` in a temporary directory and rename it to ``final``.

    Concurrent daemons never read half a split; whatever sits at ``final`` is replaced.
    """
    root = final.parent
    # Whatever sits at `final` now is stale, broken or asked to be redone.
    replace = final.exists()
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".split-", dir=root))
    try:
        make(tmp)
        if replace and final.exists():
            # Rename first, delete after: the entry vanishes at once instead of file by file.
            stale = Path(tempfile.mkdtemp(prefix=".stale-", dir=root))
            os.rename(final, stale / "old")
            shutil.rmtree(stale, ignore_errors=True)
        try:
            os.rename(tmp, final)
        except OSError:
            # Another process put the same split in place first; theirs is as good as ours.
            if not (final / MANIFEST_NAME).is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return Partition.load(final)


def _shape_key(input_shape: InputShape) -> Any:
    if input_shape is None:
        return None
    if isinstance(input_shape, Mapping):
        return {k: list(v) for k, v in sorted(input_shape.items())}
    return list(input_shape)
