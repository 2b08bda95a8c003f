"""A cloud daemon's model: the fleet's split loaded once, every suffix session built and warmed.

Every suffix shares one copy of the weights (`SplitModel`), so memory stays flat in the number of
cuts. Warming runs each suffix once on zeros at startup: nothing is built on the frame path, and
the first frame of each cut costs what later ones do; so does each segment (the part between two
cuts, for a split made with `cuts.segments`). With `batching.enabled`, each suffix is
first given a batch axis and checked against one-item runs (`SplitModel.enable_batching`); a cut
that cannot take a batch is named in the log and runs one request at a time. A suffix that cannot
run with the machine's providers stops the daemon with a `UserError` naming the cut.

Providers: each suffix session's providers (`get_providers()`) are checked against the machine's
as it is warmed (`common.providers.enforce`): a session that asked for CUDA or TensorRT and got
the CPU stops the daemon at once, naming the missing provider or library; with
`providers_fallback: allow` it serves, with one warning, and the check is kept for the probe
reply. With `gpu_serving` (on by default when the first provider is a GPU's), the sessions run
through IO binding, batched runs are padded to `batching.buckets`, and each batched suffix is
run once at every bucket, so no shape is met for the first time on a robot's frame.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from common.config import FleetConfig, MachineConfig
from common.errors import UserError
from common.fleet_model import fleet_split_model
from common.partition import TensorSpec, ort_reason
from common.partition.runtime import SplitModel
from common.providers import ProviderCheck, describe, enforce, ort_providers, prepare

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WarmSuffixes:
    """What warming found: the tensors crossing each cut, and the providers the suffix
    sessions got (`providers.fell_back`: with `providers_fallback: allow`, on fewer than
    asked)."""

    cut_specs: list[list[TensorSpec]]
    providers: ProviderCheck


def open_split_model(cfg: FleetConfig, machine: MachineConfig) -> SplitModel:
    """The fleet's model split at its cuts (from the partition cache; split on first use), with
    the machine's providers and threads, and `gpu_serving`'s IO binding and buckets; sessions
    are built later (`warm_suffixes`)."""
    prepare(machine.providers)
    gpu = machine.gpu_serving_on
    batching = machine.batching
    return fleet_split_model(
        cfg,
        providers=ort_providers(machine.providers),
        threads=machine.threads or None,
        lazy=True,
        io_binding=gpu,
        buckets=batching.bucket_sizes if gpu and batching.enabled else None,
    )


def warm_suffixes(
    model: SplitModel,
    machine: MachineConfig,
    *,
    deployment: str,
    model_name: str,
    stop: threading.Event,
) -> WarmSuffixes | None:
    """Build and run every suffix and segment once, checking each suffix's providers; None when
    `stop` was set meanwhile."""
    cut_specs = [model.cut_tensor_specs(k) for k in range(model.num_cuts)]
    unbatched: dict[int, str] = {}
    check: ProviderCheck | None = None
    warm_sizes = machine.batching.bucket_sizes if machine.gpu_serving_on else ()
    for k, specs in enumerate(cut_specs):
        if stop.is_set():
            return None
        if machine.batching.enabled:
            reason = model.enable_batching(k)
            if reason is not None:
                unbatched[k] = reason
        zeros = {s.name: np.zeros(s.shape, dtype=s.dtype) for s in specs}
        try:
            model.run_suffix(k, zeros)
            if warm_sizes and model.batched(k):
                model.warm_batches(k, warm_sizes)
        except Exception as exc:
            raise UserError(
                f"{model_name}: cannot run the suffix of cut {k} with providers "
                f"{describe(machine.providers)}: {ort_reason(exc)}"
            ) from None
        if check is None or not check.fell_back:  # one warning, not one per cut
            check = enforce(
                {f"suffix of cut {k}": model.suffix_providers(k)},
                machine.providers,
                machine.providers_fallback,
                who=deployment,
            )
    for seg in model.partition.segments:
        if stop.is_set():
            return None
        zeros = {s.name: np.zeros(s.shape, dtype=s.dtype) for s in cut_specs[seg.start]}
        try:
            model.run_segment(seg.start, seg.end, zeros)
        except Exception as exc:
            raise UserError(
                f"{model_name}: cannot run the segment from cut {seg.start} to cut {seg.end} "
                f"with providers {describe(machine.providers)}: {ort_reason(exc)}"
            ) from None
    if machine.batching.enabled:
        _log_batching(deployment, machine, model.num_cuts, unbatched)
    if machine.gpu_serving_on:
        log.info(
            "%s: gpu serving: IO binding; batched runs padded to %s and warmed at each",
            deployment,
            ", ".join(map(str, warm_sizes)) if machine.batching.enabled else "-",
        )
    assert check is not None  # a split has at least one cut
    return WarmSuffixes(cut_specs, check)


def _log_batching(
    deployment: str, machine: MachineConfig, num_cuts: int, unbatched: dict[int, str]
) -> None:
    """Say which cuts take a batch, and why the others run one request at a time."""
    batched = num_cuts - len(unbatched)
    log.info(
        "%s: batching: %d of %d cuts take a batch of up to %d",
        deployment,
        batched,
        num_cuts,
        machine.batching.max_batch,
    )
    for k, reason in unbatched.items():
        log.warning("%s: batching: cut %d runs one request at a time: %s", deployment, k, reason)
