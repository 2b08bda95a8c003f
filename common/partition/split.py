"""The partitioner's public entry points: :func:`split_model` (into a directory) and
:func:`load_partition` (through the cache), with options checked before any work.

Verification runs the cuts with the runtime that serves them, weights shared between sessions:
``runner`` builds it. By default that is the daemons' ``SplitModel`` (``runtime``, which needs
only the manifest, so nothing here is imported lazily); callers that hold a runtime of their own
pass it instead.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from common.models import ModelRef, resolve_model
from common.partition.cache import entry_dir, read_entry, write_entry
from common.partition.errors import OptionError
from common.partition.manifest import Partition
from common.partition.options import (
    DEFAULT_MAX_CUT_TENSORS,
    InputShape,
    check_max_cut_tensors,
    cuts_option,
)
from common.partition.partitioner import Partitioner
from common.partition.runtime import SplitModel
from common.partition.verify import FLOAT32_ATOL, CutRunner, RunnerFactory


def split_model(
    spec_or_path: str | Path,
    out_dir: Path | str | None = None,
    cuts: str | Sequence[str] = "auto",
    max_cut_tensors: int = DEFAULT_MAX_CUT_TENSORS,
    input_shape: InputShape = None,
    verify: bool = True,
    *,
    atol: float = FLOAT32_ATOL,
    threads: int | None = None,
    prune: bool = True,
    runner: RunnerFactory | None = None,
    segments: bool = False,
    zoo_options: Mapping[str, float] | None = None,
) -> Partition:
    """Split a model at every candidate cut (or the given ones) and write the split directory.

    ``cuts`` is ``"auto"`` or a list of cuts, each a tensor name or several joined with ``+``
    (``"a+b"``); cut 0 (the inputs) is always included. ``max_cut_tensors`` caps the tensors
    crossing an automatic cut; ``prune`` drops automatic cuts that another cut beats (same
    FLOPs on the robot, fewer bytes). ``input_shape`` fixes dynamic dimensions: a shape for the
    first input (its batch dimension may be left out) or a mapping from input name to shape.
    Cuts that fail checking or verification are listed in ``Partition.excluded`` with the reason.
    Without ``out_dir`` the split is written to the cache (as :func:`load_partition` would).
    ``runner`` builds the runtime verification runs the cuts with (default: ``SplitModel``).
    ``segments`` also writes and verifies the segment between every two cuts (segment offload:
    the cloud runs the part between them), listed in ``Partition.segments``. ``zoo_options``
    are a zoo model's build options (`common.models.resolve_model`).
    """
    if out_dir is None:
        return load_partition(
            spec_or_path, cuts, max_cut_tensors, input_shape, verify, atol=atol,
            threads=threads, prune=prune, refresh=True, runner=runner, segments=segments,
            zoo_options=zoo_options,
        )  # fmt: skip
    ref = _resolve(spec_or_path, input_shape, zoo_options)
    runner = runner or _serving_runtime
    partitioner = Partitioner(
        ref, cuts, max_cut_tensors, input_shape, verify, atol, threads, prune,
        runner=runner, segments=segments,
    )  # fmt: skip
    return partitioner.run(Path(out_dir))


def load_partition(
    spec_or_path: str | Path,
    cuts: str | Sequence[str] = "auto",
    max_cut_tensors: int = DEFAULT_MAX_CUT_TENSORS,
    input_shape: InputShape = None,
    verify: bool = True,
    *,
    atol: float = FLOAT32_ATOL,
    threads: int | None = None,
    prune: bool = True,
    refresh: bool = False,
    runner: RunnerFactory | None = None,
    segments: bool = False,
    zoo_options: Mapping[str, float] | None = None,
) -> Partition:
    """The split of a model, from the cache if it was split before with the same options.

    The cache entry is keyed by the model's sha256 digest and the options, written to a
    temporary directory and renamed into place, so concurrent daemons never read half a split.
    A zoo model built with other ``zoo_options`` (a fleet's camera geometry) is another file,
    so another digest and another entry.
    """
    parsed_cuts = cuts_option(cuts)
    check_max_cut_tensors(max_cut_tensors)
    ref = _resolve(spec_or_path, input_shape, zoo_options)
    final = entry_dir(
        ref, parsed_cuts, max_cut_tensors, input_shape, verify, atol, prune, segments=segments
    )
    if not refresh:
        cached = read_entry(final)
        if cached is not None:
            return cached
    runner = runner or _serving_runtime
    partitioner = Partitioner(
        ref, parsed_cuts, max_cut_tensors, input_shape, verify, atol, threads, prune,
        runner=runner, segments=segments,
    )  # fmt: skip
    return write_entry(final, partitioner.run)


def _resolve(
    spec_or_path: str | Path,
    input_shape: InputShape,
    zoo_options: Mapping[str, float] | None = None,
) -> ModelRef:
    zoo_shape = input_shape if not isinstance(input_shape, Mapping) else None
    if str(spec_or_path).startswith("zoo:") and isinstance(input_shape, Mapping):
        raise OptionError("input_shape", "a zoo model takes {option} as CxHxW, not NAME=shape")
    return resolve_model(spec_or_path, zoo_shape, zoo_options)


def _serving_runtime(part: Partition, threads: int | None) -> CutRunner:
    """The daemons' runtime for ``part``, sessions built per cut as verification reaches it."""
    return SplitModel(part, threads=threads, lazy=True)
