"""The ONNX partitioner: find where a model can be cut, write prefix/suffix models, verify and
run them.

A cut is a set of tensors that separates the model's inputs from its outputs: the robot computes
them with the *prefix* model (inputs → cut tensors) and the cloud finishes with the *suffix* model
(cut tensors → outputs). Candidates are positions in the model's topological order where few live
non-constant tensors cross (one in a chain; every crossing tensor in a DAG with skips). Cut 0 is
the model inputs (full offload); "everything on the robot" is not a cut.

Stages, one module each, ordered by :class:`~common.partition.partitioner.Partitioner` (in the
manner of ``onnx.utils.Extractor``): load and check the model and fix its input shapes
(``loading``), probe every tensor's dtype and shape with one onnxruntime run (``probe``), collect
the cut tensor sets and plan each cut on the dataflow graph (``candidates``, ``graph``), write the
sub-models (``builder``; weights stored once in ``weights.bin`` by ``weights``, only those
``sharing`` allows), check them with ``onnx.checker``, and verify prefix∘suffix against the full
model on seeded random input (``verify``).

A split directory holds ``manifest.json`` (``manifest``: the CLI contract), ``full.onnx``,
``weights.bin`` and ``cutNNN.prefix.onnx`` / ``cutNNN.suffix.onnx``. :func:`load_partition`
keeps one per model digest and options in the cache directory (``cache``) so daemons start
without splitting again. This module re-exports the public names; import them from here.
"""

from common.partition.candidates import DOMINATED_PREFIX
from common.partition.errors import CutError, OptionError, ort_reason
from common.partition.loading import CONSTANT_TO_INITIALIZER_BYTES, load_onnx
from common.partition.manifest import (
    FULL_NAME,
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    WEIGHTS_NAME,
    Cut,
    Partition,
    TensorSpec,
)
from common.partition.options import (
    CUT_SEPARATOR,
    DEFAULT_MAX_CUT_TENSORS,
    InputShape,
    parse_cuts,
    parse_input_shape,
)
from common.partition.runtime import SplitModel
from common.partition.split import load_partition, split_model
from common.partition.verify import (
    FLOAT16_ATOL,
    FLOAT32_ATOL,
    VERIFY_SEED,
    CutRunner,
    RunnerFactory,
    sample_feeds,
)
from common.partition.weights import EXTERNAL_MIN_BYTES, WEIGHT_ALIGN_BYTES

__all__ = [
    "CONSTANT_TO_INITIALIZER_BYTES",
    "CUT_SEPARATOR",
    "DEFAULT_MAX_CUT_TENSORS",
    "DOMINATED_PREFIX",
    "EXTERNAL_MIN_BYTES",
    "FLOAT16_ATOL",
    "FLOAT32_ATOL",
    "FULL_NAME",
    "MANIFEST_FORMAT",
    "MANIFEST_NAME",
    "VERIFY_SEED",
    "WEIGHTS_NAME",
    "WEIGHT_ALIGN_BYTES",
    "Cut",
    "CutError",
    "CutRunner",
    "InputShape",
    "OptionError",
    "Partition",
    "RunnerFactory",
    "SplitModel",
    "TensorSpec",
    "load_onnx",
    "load_partition",
    "ort_reason",
    "parse_cuts",
    "parse_input_shape",
    "sample_feeds",
    "split_model",
]
