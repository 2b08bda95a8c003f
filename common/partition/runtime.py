"""onnxruntime sessions for a split model: the full model and every cut's prefix and suffix.

The robot daemon and the cloud daemon both hold one :class:`SplitModel`. A model with K cuts needs
2K+1 sessions (plus one per segment, for a split made with segments: the cloud runs the part
between two cuts); loaded naively each would hold its own copy of the weights. Here the weights
are read once from the split's ``weights.bin`` into one buffer, and every session is handed the same
``OrtValue`` per initializer through ``SessionOptions.add_initializer``, so resident weights stay
near one copy whatever K is.

Two onnxruntime behaviours decide the session options (measured with onnxruntime 1.31):
- the NCHWc layout transformer of ``ORT_ENABLE_ALL`` re-reads convolution weights from the model
  file into a private reordered copy, so sharing needs ``ORT_ENABLE_EXTENDED``;
- weight pre-packing (MatMul/Gemm) makes a private packed copy per session, so it is disabled.
``optimization="all"`` trades that memory for the faster NCHWc kernels (each session then holds
its own convolution weights).
Each session's CPU memory arena is off by default for the same reason: an arena keeps the
session's peak activations resident, which would grow with K.

A cloud daemon that batches requests (``enable_batching``) serves a cut's suffix with a batch
axis: the partitioner writes every sub-model for one item, so the suffix is loaded into memory
with axis 0 of its inputs and outputs made symbolic (and the batch-1 shapes of intermediate
tensors dropped), built from those bytes with the same shared weights, and checked against
one-item runs before it serves. A suffix that cannot take a batch (a scalar crossing, a reshape
to a hard-coded batch of 1, results that differ) keeps running one request at a time, and the
reason is returned so the daemon can say so.

For a GPU (all off by default; the cloud daemon turns them on with `gpu_serving`):
- ``io_binding`` runs every session through an ``IOBinding``: inputs are copied to the device the
  session runs on once, as ``OrtValue``s, and outputs are allocated there and copied back after
  the run, instead of onnxruntime's per-run staging of numpy feeds and fetches;
- ``buckets`` pads a batched run up to the next of a fixed set of sizes (repeating its last
  item; the padding's results are dropped), so a batched suffix only ever sees those shapes: on
  a GPU every new shape costs a cuDNN algorithm search or a TensorRT engine build;
- ``warm_batches`` runs a batched suffix once at each of those sizes, so none of that happens on
  a robot's frame.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import onnx
import onnxruntime as ort
from onnx import helper, numpy_helper

from common.partition.errors import ort_reason
from common.partition.manifest import Partition, TensorSpec
from common.partition.verify import sample_feeds
from common.providers import GPU_PROVIDERS

Optimization = Literal["extended", "all"]
_LEVELS = {
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}
_ORT_LOG_ERROR = 3
# Where a model built from bytes finds its external weights (onnxruntime session config key).
_EXTERNAL_FOLDER_KEY = "session.model_external_initializers_file_folder_path"

ProviderArg = str | tuple[str, dict[str, str]]
"""A provider as ``onnxruntime.InferenceSession(providers=...)`` takes it (name, or name and
options; `common.providers.ort_providers`)."""

BATCH_DIM = "batch"
"""The name given to axis 0 of a batched suffix's inputs and outputs."""
BATCH_CHECK_ITEMS = 2
"""Items stacked to check a batched suffix against one-item runs (different random inputs)."""
BATCH_RTOL = 1e-4
BATCH_ATOL = 1e-5
"""Float tolerance of that check, the absolute part relative to the output's magnitude:
onnxruntime may pick other kernels (another summation order) for a bigger batch."""


class NotBatchable(Exception):
    """A sub-model cannot run on a batch of items; the message says why."""


def batch_axis_model(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    """A copy of ``model`` whose inputs and outputs take any number of items along axis 0, and
    the rows one item has there (1 for the usual batch of one).

    Every input and output must have the same static size on axis 0 (so a batch of items is
    their concatenation and each item's result is its own rows of the outputs); otherwise
    :class:`NotBatchable` names the tensor. Intermediate shapes recorded for one item
    (``value_info``) are dropped: onnxruntime infers them again for the batch.
    """
    batched = onnx.ModelProto()
    batched.CopyFrom(model)
    graph = batched.graph
    rows: set[int] = set()
    for value in [*graph.input, *graph.output]:
        if not value.type.HasField("tensor_type"):
            raise NotBatchable(f"{value.name!r} is not a tensor")
        dims = value.type.tensor_type.shape.dim
        if len(dims) == 0:
            raise NotBatchable(f"{value.name!r} is a scalar: it has no batch axis")
        if not dims[0].HasField("dim_value") or dims[0].dim_value < 1:
            raise NotBatchable(f"axis 0 of {value.name!r} has no static size")
        rows.add(int(dims[0].dim_value))
    if len(rows) != 1:
        raise NotBatchable(
            f"inputs and outputs disagree on axis 0 (sizes {', '.join(map(str, sorted(rows)))})"
        )
    for value in [*graph.input, *graph.output]:
        dim = value.type.tensor_type.shape.dim[0]
        dim.ClearField("dim_value")
        dim.dim_param = BATCH_DIM
    del graph.value_info[:]
    return batched, rows.pop()


def _same_results(expected: np.ndarray, got: np.ndarray) -> str | None:
    """None if ``got`` equals ``expected`` within the batch tolerance, else how it differs."""
    if expected.shape != got.shape or expected.dtype != got.dtype:
        return f"shape/dtype {got.shape} {got.dtype}, expected {expected.shape} {expected.dtype}"
    if not np.issubdtype(expected.dtype, np.floating):
        return None if np.array_equal(expected, got) else "values differ"
    scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    if np.allclose(got, expected, rtol=BATCH_RTOL, atol=BATCH_ATOL * scale):
        return None
    return f"max abs difference {float(np.abs(got - expected).max()):.3g}"


class SharedWeights:
    """The split's weights, read once: one numpy buffer and one OrtValue view per initializer."""

    def __init__(self, partition: Partition) -> None:
        full = onnx.load(str(partition.full), load_external_data=False)
        external: dict[str, tuple[int, int, np.dtype, tuple[int, ...]]] = {}
        inline_bytes = 0
        for t in full.graph.initializer:
            if t.data_location == onnx.TensorProto.EXTERNAL:
                info = {e.key: e.value for e in t.external_data}
                dtype = np.dtype(helper.tensor_dtype_to_np_dtype(t.data_type))
                external[t.name] = (
                    int(info.get("offset", 0)),
                    int(info["length"]),
                    dtype,
                    tuple(int(d) for d in t.dims),
                )
            else:
                inline_bytes += numpy_helper.to_array(t).nbytes
        # np.fromfile gives a writable buffer; the OrtValues below are views into it (no copy).
        self._buffer = (
            np.fromfile(partition.weights, dtype=np.uint8)
            if external
            else np.zeros(0, dtype=np.uint8)
        )
        self.arrays: dict[str, np.ndarray] = {}
        self.values: dict[str, ort.OrtValue] = {}
        for name, (offset, length, dtype, dims) in external.items():
            count = length // dtype.itemsize
            array = np.frombuffer(self._buffer, dtype=dtype, count=count, offset=offset)
            array = array.reshape(dims)
            self.arrays[name] = array
            self.values[name] = ort.OrtValue.ortvalue_from_numpy(array)
        self.nbytes = sum(a.nbytes for a in self.arrays.values()) + inline_bytes


class SplitModel:
    """Runs a split model: the whole of it, or a cut's prefix (robot) and suffix (cloud).

    ``partition`` comes from :func:`~common.partition.load_partition` (or ``split_model``).
    Sessions are built at construction unless ``lazy`` is true; either way they share one copy
    of the weights. ``segments=False`` leaves the segments' sessions out of that (a robot runs
    none: the cloud serves them; each one of a large graph holds tens of MB of session state);
    one is still built on first use. Methods are safe to call from several threads.

    ``arena`` turns on onnxruntime's CPU memory arena: slightly faster runs, but every session
    then keeps its peak activation memory (hundreds of MB over a few dozen cuts at 240x320).
    """

    def __init__(
        self,
        partition: Partition,
        providers: Sequence[ProviderArg] = ("CPUExecutionProvider",),
        threads: int | None = None,
        *,
        optimization: Optimization = "extended",
        lazy: bool = False,
        segments: bool = True,
        arena: bool = False,
        io_binding: bool = False,
        buckets: Sequence[int] | None = None,
    ) -> None:
        self.partition = partition
        if optimization not in _LEVELS:
            raise ValueError(f"optimization must be one of {', '.join(_LEVELS)}")
        if buckets is not None and (not buckets or min(buckets) < 1):
            raise ValueError(f"buckets must be sizes >= 1, got {list(buckets)}")
        self.providers = list(providers)
        self.io_binding = io_binding
        # One item always runs alone (`run_suffix_batch`), so 1 is always a bucket.
        self.buckets: tuple[int, ...] | None = (
            None if buckets is None else tuple(sorted(set(buckets) | {1}))
        )
        self.warmed: dict[int, tuple[int, ...]] = {}
        """Cut -> the batch sizes `warm_batches` ran its suffix at."""
        self.threads = threads
        self.optimization: Optimization = optimization
        self.arena = arena
        self.weights = SharedWeights(self.partition)
        self._lock = threading.Lock()
        self._full: ort.InferenceSession | None = None
        self._prefix: dict[int, ort.InferenceSession] = {}
        self._suffix: dict[int, ort.InferenceSession] = {}
        self._segment: dict[tuple[int, int], ort.InferenceSession] = {}
        self._batch_rows: dict[int, int] = {}  # cut -> rows of one item, for batched suffixes
        if not lazy:
            self.build_all(segments=segments)

    # -- facts --

    @property
    def digest(self) -> str:
        return self.partition.digest

    @property
    def input_names(self) -> list[str]:
        return list(self.partition.inputs)

    @property
    def output_names(self) -> list[str]:
        return list(self.partition.outputs)

    @property
    def num_cuts(self) -> int:
        return len(self.partition.cuts)

    @property
    def weight_bytes(self) -> int:
        """Bytes of the model's weights (initializers), counted once."""
        return self.weights.nbytes

    def input_specs(self) -> list[TensorSpec]:
        return [self.partition.specs[n] for n in self.partition.inputs]

    def cut_tensor_specs(self, k: int) -> list[TensorSpec]:
        """Name, dtype and shape of every tensor crossing cut ``k`` (what the cloud receives)."""
        return self.partition.cut_specs(k)

    # -- running --

    def run_full(
        self, feeds: Mapping[str, np.ndarray], *, run_options: ort.RunOptions | None = None
    ) -> dict[str, np.ndarray]:
        """The whole model on this host: model inputs → model outputs.

        ``run_options`` (all ``run_*`` methods) is handed to ``InferenceSession.run``: another
        thread may set its ``terminate`` to stop the run, which then raises."""
        session = self._full_session()
        return self._run(session, feeds, "the full model", run_options)

    def run_prefix(
        self,
        k: int,
        feeds: Mapping[str, np.ndarray],
        *,
        run_options: ort.RunOptions | None = None,
    ) -> dict[str, np.ndarray]:
        """The robot's part of cut ``k``: model inputs → the cut's tensors, by name.

        Model inputs that cross the cut (all of them for cut 0) are passed through as given.
        """
        cut = self.partition.cut(k)
        out: dict[str, np.ndarray] = {}
        if cut.prefix is not None:
            out = self._run(self._prefix_session(k), feeds, f"prefix of cut {k}", run_options)
        inputs = set(self.partition.inputs)
        missing = [t for t in cut.tensors if t in inputs and t not in feeds]
        if missing:
            raise ValueError(f"prefix of cut {k}: missing model input(s) {', '.join(missing)}")
        for name in cut.tensors:
            if name in inputs:
                out[name] = np.asarray(feeds[name])
        return {name: out[name] for name in cut.tensors}

    def run_suffix(
        self,
        k: int,
        tensors: Mapping[str, np.ndarray],
        feeds: Mapping[str, np.ndarray] | None = None,
        *,
        run_options: ort.RunOptions | None = None,
    ) -> dict[str, np.ndarray]:
        """The cloud's part of cut ``k``: the cut's tensors → model outputs.

        A model input the suffix still needs may come in ``tensors`` or in ``feeds``.
        """
        cut = self.partition.cut(k)
        given: dict[str, np.ndarray] = {}
        missing = []
        for name in cut.tensors:
            if name in tensors:
                given[name] = tensors[name]
            elif feeds is not None and name in feeds:
                given[name] = feeds[name]
            else:
                missing.append(name)
        if missing:
            raise ValueError(f"suffix of cut {k}: missing tensor(s) {', '.join(missing)}")
        return self._run(self._suffix_session(k), given, f"suffix of cut {k}", run_options)

    def has_segment(self, start: int, end: int) -> bool:
        """Whether the split has the segment from cut ``start`` to cut ``end``."""
        return self.partition.has_segment(start, end)

    def run_segment(
        self,
        start: int,
        end: int,
        tensors: Mapping[str, np.ndarray],
        *,
        run_options: ort.RunOptions | None = None,
    ) -> dict[str, np.ndarray]:
        """The cloud's part of a segment: cut ``start``'s tensors → cut ``end``'s, by name.

        Tensors of cut ``end`` that also cross cut ``start`` (a skip over the whole segment) are
        passed through as given, like model inputs through a prefix.
        """
        self.partition.segment(start, end)  # ValueError naming the segments there are
        given = set(self.partition.cut(start).tensors)
        missing = [t for t in given if t not in tensors]
        if missing:
            raise ValueError(
                f"segment {start}-{end}: missing tensor(s) {', '.join(sorted(missing))}"
            )
        session = self._segment_session(start, end)
        out = self._run(session, tensors, f"segment {start}-{end}", run_options)
        for name in self.partition.cut(end).tensors:
            if name in given:
                out[name] = np.asarray(tensors[name])
        return {name: out[name] for name in self.partition.cut(end).tensors}

    def enable_batching(self, k: int, *, check_items: int = BATCH_CHECK_ITEMS) -> str | None:
        """Serve cut ``k``'s suffix with a batch axis (see the module docstring), replacing its
        one-item session. Returns None when it does, else why it cannot (the suffix then keeps
        running one request at a time). Meant for startup, before the suffix serves."""
        cut = self.partition.cut(k)
        assert cut.suffix is not None
        try:
            batched, rows = batch_axis_model(onnx.load(str(cut.suffix), load_external_data=False))
            session = self._session(batched)
        except NotBatchable as exc:
            return str(exc)
        except Exception as exc:  # onnxruntime refuses the batched model
            return f"onnxruntime cannot load it with a batch axis: {ort_reason(exc)}"
        specs = self.cut_tensor_specs(k)
        items = [sample_feeds(specs, seed=seed) for seed in range(check_items)]
        try:
            expected = [self.run_suffix(k, item) for item in items]
            outputs = self._run(session, self._stack(items), f"batched suffix of cut {k}")
            got = self._split(outputs, rows, len(items))
        except Exception as exc:
            return f"a batch of {check_items} fails: {ort_reason(exc)}"
        for i, (want, have) in enumerate(zip(expected, got, strict=True)):
            for name, value in want.items():
                problem = _same_results(value, have[name])
                if problem is not None:
                    return f"item {i} of a batch differs from its own run on {name!r}: {problem}"
        with self._lock:
            self._suffix[k] = session
            self._batch_rows[k] = rows
        return None

    def batched(self, k: int) -> bool:
        """Whether cut ``k``'s suffix takes a batch (``enable_batching`` succeeded)."""
        with self._lock:
            return k in self._batch_rows

    def run_suffix_batch(
        self,
        k: int,
        items: Sequence[Mapping[str, np.ndarray]],
        *,
        run_options: ort.RunOptions | None = None,
    ) -> list[dict[str, np.ndarray]]:
        """Cut ``k``'s suffix on several items (each the cut's tensors, as ``run_suffix`` takes
        them) in one run when the suffix takes a batch, else one run per item. Each result is
        that item's own rows of the outputs."""
        with self._lock:
            rows = self._batch_rows.get(k)
        if rows is None or len(items) == 1:
            return [self.run_suffix(k, item, run_options=run_options) for item in items]
        cut = self.partition.cut(k)
        for item in items:
            missing = [name for name in cut.tensors if name not in item]
            if missing:
                raise ValueError(f"suffix of cut {k}: missing tensor(s) {', '.join(missing)}")
            bad = [n for n in cut.tensors if np.ndim(item[n]) == 0 or len(item[n]) != rows]
            if bad:
                raise ValueError(
                    f"suffix of cut {k}: {', '.join(bad)} must have {rows} row(s) on axis 0"
                )
        size = self.bucket_for(len(items))
        # Padding repeats the last item (real values: no NaN or overflow from made-up ones).
        padded = [*items, *[items[-1]] * (size - len(items))]
        outputs = self._run(
            self._suffix_session(k), self._stack(padded), f"batched suffix of cut {k}", run_options
        )
        return self._split(outputs, rows, size)[: len(items)]

    def bucket_for(self, n: int) -> int:
        """The batch size a run of ``n`` items is padded up to: the smallest bucket that holds
        them (``n`` itself without buckets, or beyond the largest)."""
        if self.buckets is None:
            return n
        return next((b for b in self.buckets if b >= n), n)

    def warm_batches(self, k: int, sizes: Sequence[int]) -> None:
        """Run cut ``k``'s batched suffix once at each of ``sizes`` (on zeros), so that the
        shapes a batcher forms are not met for the first time on a robot's frame. Each size
        goes through `run_suffix_batch`, so buckets apply; `warmed` records the sizes run."""
        if not self.batched(k):
            raise ValueError(f"cut {k}: its suffix takes no batch (enable_batching first)")
        specs = self.cut_tensor_specs(k)
        item = {s.name: np.zeros(s.shape, dtype=s.dtype) for s in specs}
        ran: list[int] = []
        for n in sorted(set(sizes)):
            self.run_suffix_batch(k, [item] * n)
            ran.append(self.bucket_for(n))
        self.warmed[k] = tuple(sorted(set(ran)))

    def suffix_providers(self, k: int) -> list[str]:
        """The providers cut ``k``'s suffix session really got (``get_providers()``; onnxruntime
        falls back to the CPU without raising, `common.providers.check_session`)."""
        return list(self._suffix_session(k).get_providers())

    def session_providers(self) -> dict[str, list[str]]:
        """Every session built so far -> the providers it got, named as in errors."""
        with self._lock:
            named: list[tuple[str, ort.InferenceSession]] = []
            if self._full is not None:
                named.append(("the full model", self._full))
            named += [(f"prefix of cut {k}", s) for k, s in sorted(self._prefix.items())]
            named += [(f"suffix of cut {k}", s) for k, s in sorted(self._suffix.items())]
            named += [(f"segment {a}-{b}", s) for (a, b), s in sorted(self._segment.items())]
        return {what: list(session.get_providers()) for what, session in named}

    @staticmethod
    def _stack(items: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {name: np.concatenate([item[name] for item in items]) for name in items[0]}

    @staticmethod
    def _split(
        outputs: Mapping[str, np.ndarray], rows: int, count: int
    ) -> list[dict[str, np.ndarray]]:
        for name, value in outputs.items():
            if np.ndim(value) == 0 or len(value) != rows * count:
                shape = np.shape(value)
                raise ValueError(
                    f"output {name!r} has shape {shape} for {count} item(s) of {rows} row(s)"
                )
        return [
            {name: value[i * rows : (i + 1) * rows] for name, value in outputs.items()}
            for i in range(count)
        ]

    def build_all(self, *, segments: bool = True) -> None:
        """Build every session now (startup cost paid once, nothing built on the frame path);
        the segments' too unless ``segments`` is false."""
        self._full_session()
        for k, cut in enumerate(self.partition.cuts):
            if cut.prefix is not None:
                self._prefix_session(k)
            self._suffix_session(k)
        if not segments:
            return
        for seg in self.partition.segments:
            self._segment_session(seg.start, seg.end)

    def release(self, k: int) -> None:
        """Drop cut ``k``'s sessions and its segments' (they are rebuilt on next use)."""
        with self._lock:
            self._prefix.pop(k, None)
            self._suffix.pop(k, None)
            for pair in [p for p in self._segment if k in p]:
                del self._segment[pair]

    def close(self) -> None:
        """Drop every session; the object can still be used and rebuilds them lazily."""
        with self._lock:
            self._full = None
            self._prefix.clear()
            self._suffix.clear()
            self._segment.clear()

    def __enter__(self) -> SplitModel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- sessions --

    def _run(
        self,
        session: ort.InferenceSession,
        feeds: Mapping[str, np.ndarray],
        what: str,
        run_options: ort.RunOptions | None = None,
    ) -> dict[str, np.ndarray]:
        names = [i.name for i in session.get_inputs()]
        missing = [n for n in names if n not in feeds]
        if missing:
            raise ValueError(f"{what}: missing input(s) {', '.join(missing)}")
        outputs = [o.name for o in session.get_outputs()]
        if self.io_binding:
            return self._run_bound(session, names, outputs, feeds, run_options)
        values = session.run(outputs, {n: feeds[n] for n in names}, run_options)
        return dict(zip(outputs, values, strict=True))

    def _run_bound(
        self,
        session: ort.InferenceSession,
        names: Sequence[str],
        outputs: Sequence[str],
        feeds: Mapping[str, np.ndarray],
        run_options: ort.RunOptions | None,
    ) -> dict[str, np.ndarray]:
        """One run through an IOBinding: inputs copied to the session's device once, outputs
        allocated there by onnxruntime and copied back to numpy after the run."""
        device, device_id = self._device(session)
        binding = session.io_binding()
        for name in names:
            value = np.ascontiguousarray(feeds[name])
            if device == "cpu":
                binding.bind_cpu_input(name, value)
            else:
                on_device = ort.OrtValue.ortvalue_from_numpy(value, device, device_id)
                binding.bind_ortvalue_input(name, on_device)
        for name in outputs:
            binding.bind_output(name, device, device_id)
        session.run_with_iobinding(binding, run_options)
        values = binding.copy_outputs_to_cpu()
        return dict(zip(outputs, values, strict=True))

    def _device(self, session: ort.InferenceSession) -> tuple[str, int]:
        """Where a session's inputs and outputs live: the GPU of its first provider when that is
        CUDA or TensorRT (and the session really got it), else the CPU."""
        first = session.get_providers()[0]
        if first not in GPU_PROVIDERS:
            return "cpu", 0
        options = session.get_provider_options().get(first, {})
        return "cuda", int(options.get("device_id", 0))

    def _full_session(self) -> ort.InferenceSession:
        with self._lock:
            if self._full is None:
                self._full = self._session(self.partition.full)
            return self._full

    def _prefix_session(self, k: int) -> ort.InferenceSession:
        cut = self.partition.cut(k)
        with self._lock:
            session = self._prefix.get(k)
            if session is None:
                assert cut.prefix is not None
                session = self._prefix[k] = self._session(cut.prefix)
            return session

    def _suffix_session(self, k: int) -> ort.InferenceSession:
        cut = self.partition.cut(k)
        with self._lock:
            session = self._suffix.get(k)
            if session is None:
                assert cut.suffix is not None
                session = self._suffix[k] = self._session(cut.suffix)
            return session

    def _segment_session(self, start: int, end: int) -> ort.InferenceSession:
        path = self.partition.segment(start, end).path
        with self._lock:
            session = self._segment.get((start, end))
            if session is None:
                session = self._segment[(start, end)] = self._session(path)
            return session

    def _session(self, model: Path | onnx.ModelProto) -> ort.InferenceSession:
        """A session of a model file, or of a model in memory (its external weights are then
        found in the split's directory, and all of them are the shared ones anyway)."""
        opts = ort.SessionOptions()
        opts.log_severity_level = _ORT_LOG_ERROR
        opts.graph_optimization_level = _LEVELS[self.optimization]
        if self.threads:
            opts.intra_op_num_threads = self.threads
            opts.inter_op_num_threads = 1
        # Daemons share a host's cores (and a robot may run under a CPU quota): idle onnxruntime
        # workers that spin burn the cores the other processes need.
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if not self.arena:
            opts.enable_cpu_mem_arena = False
        if self.optimization == "extended":
            opts.add_session_config_entry("session.disable_prepacking", "1")
        # Every session gets every shared weight; onnxruntime ignores the ones a sub-model lacks.
        for name, value in self.weights.values.items():
            opts.add_initializer(name, value)
        if isinstance(model, onnx.ModelProto):
            opts.add_session_config_entry(_EXTERNAL_FOLDER_KEY, str(self.partition.dir))
            return ort.InferenceSession(model.SerializeToString(), opts, providers=self.providers)
        return ort.InferenceSession(str(model), opts, providers=self.providers)
