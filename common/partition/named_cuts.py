"""Cuts a model names in its metadata: ``elasticfog.cut.<name>`` = the cut's tensors joined by
``+`` (zoo:stereo names ``points``), mapped to the split's cut indices so that an application
can say "offload up to the points" without knowing how the partitioner numbered the cuts."""

from __future__ import annotations

import onnx

from common.partition.manifest import Partition
from common.partition.options import CUT_SEPARATOR

NAMED_CUT_PREFIX = "elasticfog.cut."


def named_cuts(part: Partition) -> dict[str, int]:
    """{name: cut index} of the cuts the model names that the split has (a named cut the split
    left out, or pruned, is not listed)."""
    model = onnx.load(str(part.full), load_external_data=False)
    by_tensors = {frozenset(cut.tensors): cut.index for cut in part.cuts}
    found: dict[str, int] = {}
    for prop in model.metadata_props:
        if not prop.key.startswith(NAMED_CUT_PREFIX):
            continue
        tensors = frozenset(t.strip() for t in prop.value.split(CUT_SEPARATOR) if t.strip())
        index = by_tensors.get(tensors)
        if index is not None:
            found[prop.key[len(NAMED_CUT_PREFIX) :]] = index
    return found
