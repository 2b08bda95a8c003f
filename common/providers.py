"""onnxruntime execution providers: the names a fleet file may use, their options, and the check
that a session really runs on what was asked for.

Names (a contract): `cpu`, `cuda`, `tensorrt`, or any onnxruntime provider name
(`CUDAExecutionProvider`, ...: what a machine's `providers` took before the short names). An
entry is a name, or a one-key mapping of a name to its options:

    providers: [cuda, cpu]
    providers:
      - tensorrt: {device_id: 0, engine_cache: trt/engines, timing_cache: trt/timing}
      - cuda: {device_id: 0}
      - cpu

Each entry is parsed into a `ProviderSpec` when the config is read (an unknown name or option
fails there, with the known ones listed); `ort_providers` turns them into what
`onnxruntime.InferenceSession(providers=...)` takes.

Why a check: onnxruntime does not raise when an accelerator's provider is missing from its build
or its libraries do not load; it logs a line on stderr and the session runs on
CPUExecutionProvider. A deployment asked to serve from a GPU would then serve from the CPU
without anyone knowing. `check_session` compares what a session reports (`get_providers()`)
with what was asked and `missing_reason` names the cause: the provider is not in this
onnxruntime build (with the ones it has), a shared library does not load (the dynamic loader's
own message, which names the first library it could not find), or the driver sees no GPU.
"""

from __future__ import annotations

import contextlib
import ctypes
import enum
import io
import logging
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import onnxruntime as ort

log = logging.getLogger(__name__)


class ProviderName(str, enum.Enum):
    """The short names a fleet file may use."""

    CPU = "cpu"
    CUDA = "cuda"
    TENSORRT = "tensorrt"


class ProviderFallback(str, enum.Enum):
    """What a daemon does when a session did not get an accelerator it asked for."""

    REFUSE = "refuse"
    """Stop at start with a one-line error naming the missing provider or library."""
    ALLOW = "allow"
    """Serve on what the session got, with a warning and a flag in the deployment's probe reply."""


ORT_NAME = {
    ProviderName.CPU: "CPUExecutionProvider",
    ProviderName.CUDA: "CUDAExecutionProvider",
    ProviderName.TENSORRT: "TensorrtExecutionProvider",
}
CPU_PROVIDER = ORT_NAME[ProviderName.CPU]
GPU_PROVIDERS = frozenset({ORT_NAME[ProviderName.CUDA], ORT_NAME[ProviderName.TENSORRT]})
"""Providers that run on an NVIDIA GPU (IO binding then binds to the `cuda` device)."""

# onnxruntime's own provider names (`onnxruntime.get_all_providers()` of onnxruntime 1.32 and
# onnxruntime-gpu 1.31): a machine's `providers` took these before the short names existed, and
# still does. A unit test checks that every name onnxruntime knows is here.
ORT_PROVIDER_NAMES: tuple[str, ...] = (
    "TensorrtExecutionProvider",
    "CUDAExecutionProvider",
    "MIGraphXExecutionProvider",
    "ROCMExecutionProvider",
    "OpenVINOExecutionProvider",
    "DnnlExecutionProvider",
    "VitisAIExecutionProvider",
    "QNNExecutionProvider",
    "NnapiExecutionProvider",
    "VSINPUExecutionProvider",
    "JsExecutionProvider",
    "CoreMLExecutionProvider",
    "ArmNNExecutionProvider",
    "ACLExecutionProvider",
    "NvTensorRTRTXExecutionProvider",
    "DmlExecutionProvider",
    "RknpuExecutionProvider",
    "WebNNExecutionProvider",
    "WebGpuExecutionProvider",
    "XnnpackExecutionProvider",
    "CANNExecutionProvider",
    "AzureExecutionProvider",
    "CPUExecutionProvider",
)

# Options each provider takes in a fleet file (others take none).
_OPTIONS: dict[str, tuple[str, ...]] = {
    ORT_NAME[ProviderName.CUDA]: ("device_id",),
    ORT_NAME[ProviderName.TENSORRT]: ("device_id", "engine_cache", "timing_cache"),
}
_SHORT = {ort_name: short for short, ort_name in ORT_NAME.items()}


@dataclass(frozen=True)
class ProviderSpec:
    """One provider of a machine, parsed: onnxruntime's name and the options the file gave.

    `engine_cache` and `timing_cache` (TensorRT) are folders; relative ones are relative to the
    fleet file (the config resolves them)."""

    ort_name: str
    device_id: int | None = None
    engine_cache: str | None = None
    timing_cache: str | None = None

    @property
    def short(self) -> ProviderName | None:
        """The short name, for the three that have one."""
        return _SHORT.get(self.ort_name)

    @property
    def label(self) -> str:
        """How the fleet file's reader knows it: the short name, else onnxruntime's."""
        return self.short.value if self.short is not None else self.ort_name

    @property
    def gpu(self) -> bool:
        """Runs on an NVIDIA GPU (CUDA or TensorRT)."""
        return self.ort_name in GPU_PROVIDERS

    def ort_options(self) -> dict[str, str]:
        """onnxruntime's provider options for this entry (strings, as onnxruntime takes them)."""
        options: dict[str, str] = {}
        if self.device_id is not None:
            options["device_id"] = str(self.device_id)
        if self.engine_cache is not None:
            options["trt_engine_cache_enable"] = "True"
            options["trt_engine_cache_path"] = self.engine_cache
        if self.timing_cache is not None:
            options["trt_timing_cache_enable"] = "True"
            options["trt_timing_cache_path"] = self.timing_cache
        return options

    def to_config(self) -> str | dict[str, dict[str, Any]]:
        """The fleet-file form (what `parse_provider` reads back)."""
        options: dict[str, Any] = {
            k: v
            for k, v in (
                ("device_id", self.device_id),
                ("engine_cache", self.engine_cache),
                ("timing_cache", self.timing_cache),
            )
            if v is not None
        }
        return {self.label: options} if options else self.label

    def with_paths(self, resolve: Any) -> ProviderSpec:
        """This entry with its cache folders passed through `resolve` (str -> str)."""
        if self.engine_cache is None and self.timing_cache is None:
            return self
        return ProviderSpec(
            self.ort_name,
            self.device_id,
            None if self.engine_cache is None else resolve(self.engine_cache),
            None if self.timing_cache is None else resolve(self.timing_cache),
        )


def known_names() -> str:
    """The names a fleet file may use, for error messages."""
    return ", ".join([p.value for p in ProviderName] + ["or an onnxruntime provider name"])


def _ort_name(name: str) -> str:
    try:
        return ORT_NAME[ProviderName(name)]
    except ValueError:
        pass
    if name in ORT_PROVIDER_NAMES:
        return name
    raise ValueError(f"unknown provider {name!r}; known: {known_names()}")


def parse_provider(value: object) -> ProviderSpec:
    """A fleet file's provider entry (a name, or `{name: {options}}`) -> `ProviderSpec`;
    ValueError naming the unknown name or option, with the known ones."""
    if isinstance(value, ProviderSpec):
        return value
    if isinstance(value, str):
        return ProviderSpec(_ort_name(value))
    if not (isinstance(value, Mapping) and len(value) == 1):
        raise ValueError(
            f"{value!r} is not a provider; expected a name ({known_names()}) or "
            "{name: {option: value}}"
        )
    ((name, options),) = value.items()
    if not isinstance(name, str):
        raise ValueError(f"{name!r} is not a provider name; known: {known_names()}")
    ort_name = _ort_name(name)
    options = {} if options is None else options
    if not isinstance(options, Mapping):
        raise ValueError(f"{name}: options must be a mapping, got {options!r}")
    allowed = _OPTIONS.get(ort_name, ())
    unknown = [str(k) for k in options if k not in allowed]
    if unknown:
        raise ValueError(
            f"{name}: unknown option(s) {', '.join(unknown)}; options: "
            f"{', '.join(allowed) or 'none'}"
        )
    device_id = options.get("device_id")
    if device_id is not None and (
        not isinstance(device_id, int) or isinstance(device_id, bool) or device_id < 0
    ):
        raise ValueError(f"{name}: device_id must be an integer >= 0, got {device_id!r}")
    paths = {}
    for key in ("engine_cache", "timing_cache"):
        folder = options.get(key)
        if folder is not None and (not isinstance(folder, str) or not folder):
            raise ValueError(f"{name}: {key} must be a folder path, got {folder!r}")
        paths[key] = folder
    return ProviderSpec(ort_name, device_id, paths["engine_cache"], paths["timing_cache"])


def check_list(specs: Sequence[ProviderSpec]) -> None:
    """A machine's list as a whole: no provider twice; ValueError otherwise."""
    seen: set[str] = set()
    for spec in specs:
        if spec.ort_name in seen:
            raise ValueError(f"{spec.label} is listed twice")
        seen.add(spec.ort_name)


def ort_providers(specs: Sequence[ProviderSpec]) -> list[str | tuple[str, dict[str, str]]]:
    """What `onnxruntime.InferenceSession(providers=...)` takes for these entries."""
    out: list[str | tuple[str, dict[str, str]]] = []
    for spec in specs:
        options = spec.ort_options()
        out.append((spec.ort_name, options) if options else spec.ort_name)
    return out


def describe(specs: Sequence[ProviderSpec]) -> str:
    """`cuda, cpu` for a log line."""
    return ", ".join(s.label for s in specs)


def prepare(specs: Sequence[ProviderSpec]) -> None:
    """Before sessions are built: where a GPU provider is asked for, let onnxruntime-gpu load
    the CUDA and cuDNN libraries of the `nvidia-*` wheels (they are not on the loader's path;
    `onnxruntime.preload_dlls`, which does nothing in a CPU build). What it prints goes to the
    log."""
    if not any(s.gpu for s in specs):
        return
    import onnxruntime as ort

    preload = getattr(ort, "preload_dlls", None)
    if preload is None:
        return
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        try:
            preload()
        except Exception as exc:  # a failed preload is diagnosed by the check, not here
            log.debug("onnxruntime.preload_dlls: %s", exc)
    for line in printed.getvalue().splitlines():
        if line.strip():
            log.info("onnxruntime.preload_dlls: %s", line.strip())


@dataclass(frozen=True)
class ProviderCheck:
    """What a session was asked for and what it got. `missing`: asked-for providers (other than
    the CPU) the session does not have, each with why (`missing_reason`)."""

    asked: tuple[str, ...]
    got: tuple[str, ...]
    missing: tuple[tuple[str, str], ...] = ()

    @property
    def fell_back(self) -> bool:
        return bool(self.missing)

    def message(self) -> str:
        """One line: what was asked, what runs, and why the rest is missing."""
        why = "; ".join(reason for _, reason in self.missing)
        return (
            f"asked for {', '.join(self.asked)} but the session runs on "
            f"{', '.join(self.got) or 'nothing'}: {why}"
        )


def check_session(
    session: ort.InferenceSession | Sequence[str], specs: Sequence[ProviderSpec]
) -> ProviderCheck:
    """Compare the providers `session` got (or a list of them) with `specs`."""
    got = tuple(session if isinstance(session, Sequence) else session.get_providers())
    asked = tuple(s.ort_name for s in specs)
    missing = tuple(
        (s.ort_name, missing_reason(s))
        for s in specs
        if s.ort_name != CPU_PROVIDER and s.ort_name not in got
    )
    return ProviderCheck(asked, got, missing)


def missing_reason(spec: ProviderSpec) -> str:
    """Why onnxruntime did not give a session `spec`'s provider, as far as can be told from here:
    not in the build, a library that does not load, no NVIDIA driver or GPU, or (none of these)
    onnxruntime's own log line."""
    import onnxruntime as ort

    name = spec.ort_name
    available = ort.get_available_providers()
    if name not in available:
        package = _ort_package()
        hint = " (install elasticfog[gpu], onnxruntime-gpu, instead)" if spec.gpu else ""
        return (
            f"{name} is not in this onnxruntime build ({package} {ort.__version__} has "
            f"{', '.join(available)}){hint}"
        )
    if spec.gpu and sys.platform.startswith("linux"):
        reason = _library_problem(name) or _driver_problem(spec.device_id or 0)
        if reason is not None:
            return f"{name}: {reason}"
    return f"{name} is in this build but onnxruntime did not create it (its log line says why)"


def _ort_package() -> str:
    try:
        from onnxruntime.capi import build_and_package_info as info

        return str(info.package_name)
    except ImportError:
        return "onnxruntime"


_PROVIDER_LIBRARY = {
    ORT_NAME[ProviderName.CUDA]: "libonnxruntime_providers_cuda.so",
    ORT_NAME[ProviderName.TENSORRT]: "libonnxruntime_providers_tensorrt.so",
}


def _library_problem(name: str) -> str | None:
    """Load the provider's library the way onnxruntime does (after its shared provider library,
    globally); the loader's message names the first dependency it cannot find (libcudart,
    libcublasLt, libcudnn, libnvinfer ...)."""
    import onnxruntime as ort

    capi = Path(ort.__file__).parent / "capi"
    library = capi / _PROVIDER_LIBRARY[name]
    if not library.exists():
        return f"{library.name} is not in {capi}"
    try:
        ctypes.CDLL(str(capi / "libonnxruntime_providers_shared.so"), mode=ctypes.RTLD_GLOBAL)
        ctypes.CDLL(str(library))
    except OSError as exc:
        return f"{library.name} does not load: {exc}"
    return None


def _driver_problem(device_id: int) -> str | None:
    """No driver (libcuda), a driver that does not start, or no GPU at `device_id`."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError as exc:
        return f"no NVIDIA driver: {exc}"
    status = cuda.cuInit(0)
    if status != 0:
        return f"the NVIDIA driver does not start (cuInit returned CUDA error {status})"
    count = ctypes.c_int(0)
    status = cuda.cuDeviceGetCount(ctypes.byref(count))
    if status != 0:
        return f"cuDeviceGetCount returned CUDA error {status}"
    if device_id >= count.value:
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        where = f" (CUDA_VISIBLE_DEVICES={visible})" if visible is not None else ""
        return f"device_id {device_id} asked but {count.value} GPU(s) visible{where}"
    return None


def enforce(
    sessions: Mapping[str, Sequence[str]],
    specs: Sequence[ProviderSpec],
    fallback: ProviderFallback,
    *,
    who: str,
) -> ProviderCheck:
    """Check each session (what -> the providers it got) against `specs`. The first that did
    not get an accelerator it asked for: with REFUSE a one-line `UserError` naming the missing
    provider and why; with ALLOW one warning, and its check is returned (`fell_back`). None
    fell back: the check of the first session."""
    from common.errors import UserError

    first: ProviderCheck | None = None
    for what, got in sessions.items():
        check = check_session(got, specs)
        first = first or check
        if not check.fell_back:
            continue
        line = f"{who}: {what}: {check.message()}"
        if fallback is ProviderFallback.REFUSE:
            raise UserError(f"{line} (providers_fallback: allow would serve on it instead)")
        log.warning("%s; serving on %s (providers_fallback: allow)", line, ", ".join(check.got))
        return check
    return first or ProviderCheck(tuple(s.ort_name for s in specs), ())


def cuda_ready(device_id: int = 0) -> bool:
    """Whether a CUDA session could get its GPU here: onnxruntime-gpu, its CUDA libraries and
    a driver that sees GPU `device_id` (what the GPU-only tests ask before they run)."""
    import onnxruntime as ort

    cuda = ORT_NAME[ProviderName.CUDA]
    if cuda not in ort.get_available_providers() or not sys.platform.startswith("linux"):
        return False
    prepare([ProviderSpec(cuda)])
    return _library_problem(cuda) is None and _driver_problem(device_id) is None
