"""A handler as the runtime's model (`common.handlers`): a `SplitModel` over the identity graph
of the handler's image, whose only cut is 0, and whose full run and cut-0 suffix call the
handler. Apart from `common.handlers` so that reading a fleet file (which checks that a handler
imports) does not load onnxruntime."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import onnxruntime as ort

from common.handlers import HANDLER_INPUT, Handler
from common.partition import Partition
from common.partition.runtime import SplitModel

NO_BATCHING = "a handler runs one frame at a time"


class HandlerModel(SplitModel):
    """`HandlerModel(partition, handler, **SplitModel options)`: `partition` is the identity
    graph's (`common.handlers.identity_model_path`). Opening it calls the handler once on a
    blank image to learn its outputs (a `HandlerError` if that fails)."""

    def __init__(self, partition: Partition, handler: Handler, **options: Any) -> None:
        super().__init__(partition, **options)
        self.handler = handler
        handler.learn_outputs(partition.specs[HANDLER_INPUT].shape)
        self._digest = handler.digest()

    @property
    def digest(self) -> str:
        return self._digest

    @property
    def output_names(self) -> list[str]:
        return list(self.handler.outputs or {})

    def run_full(
        self, feeds: Mapping[str, np.ndarray], *, run_options: ort.RunOptions | None = None
    ) -> dict[str, np.ndarray]:
        return self.handler({HANDLER_INPUT: np.asarray(feeds[HANDLER_INPUT])})

    def run_suffix(
        self,
        k: int,
        tensors: Mapping[str, np.ndarray],
        feeds: Mapping[str, np.ndarray] | None = None,
        *,
        run_options: ort.RunOptions | None = None,
    ) -> dict[str, np.ndarray]:
        if k != 0:
            raise ValueError(f"a handler has one cut, 0; got cut {k}")
        image = tensors.get(HANDLER_INPUT)
        if image is None and feeds is not None:
            image = feeds.get(HANDLER_INPUT)
        if image is None:
            raise ValueError(f"suffix of cut 0: missing tensor {HANDLER_INPUT}")
        return self.handler({HANDLER_INPUT: np.asarray(image)})

    def enable_batching(self, k: int, *, check_items: int = 0) -> str | None:
        return NO_BATCHING
