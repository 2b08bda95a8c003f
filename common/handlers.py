"""Services that are not networks: Python handlers (`services.<name>.handler: module:function`).

A handler is called with a frame's inputs, `{"image": uint8 1xHxWx3 RGB}` (the camera image
resized like a model's input to the service's `input_shape`), and the service's `params` as
keyword arguments; it returns `{name: numpy array}`. It runs whole, on the robot (action P) or on
a deployment (cut 0: the image crosses with any image codec), so the runtime treats it as a model
whose only cut is 0: `HandlerModel` is a `SplitModel` over a one-node identity graph of the image
(the cut, its tensor specs, the codecs and the profiles work unchanged), whose full run and suffix
call the handler on the image. Its digest covers the handler's spec, its params and the source of
its module (and of the modules beside it in its package), so a robot and a deployment running
different code are told apart like different models.

A handler that raises or returns something other than a mapping of names to numeric arrays is a
`HandlerError` naming the handler and the problem: the deployment answers a named error reply
(the robot then finishes the frame itself) and keeps serving. The names and dtypes of its outputs
are learned from a first call on a blank image when the model opens (a handler whose outputs
change name or dtype later is refused the same way); their shapes may vary from frame to frame (a
detector finds as many tags as there are).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import UserError

HANDLER_INPUT = "image"
"""The name of a handler's one input: the camera image, uint8 1xHxWx3 RGB."""
IDENTITY_OUTPUT = "image_out"
IDENTITY_FORMAT = 1
"""Bumped when the identity graph changes (it names the cached file)."""


class HandlerError(Exception):
    """A handler raised, or returned something that is not {name: numeric numpy array}."""


@contextmanager
def _search_first(folder: Path | None) -> Iterator[None]:
    """Import with `folder` (the fleet file's) searched first, as a user's project folder."""
    if folder is None:
        yield
        return
    sys.path.insert(0, str(folder))
    try:
        yield
    finally:
        with suppress(ValueError):
            sys.path.remove(str(folder))


def import_handler(spec: str, base_dir: Path | None = None) -> Callable[..., Any]:
    """The function `module:function` names; UserError (one line) when the module does not
    import, has no such attribute, or it is not callable."""
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise UserError(f"handler {spec!r}: expected module:function, e.g. mypkg.tags:detect")
    with _search_first(base_dir):
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:  # any error the user's module raises while importing
            raise UserError(
                f"handler {spec!r}: module {module_name!r} does not import: "
                f"{type(exc).__name__}: {exc}"
            ) from None
    fn = module
    for part in attr.split("."):
        if not hasattr(fn, part):
            raise UserError(f"handler {spec!r}: module {module_name!r} has no {attr!r}")
        fn = getattr(fn, part)
    if not callable(fn):
        raise UserError(f"handler {spec!r}: {attr!r} is a {type(fn).__name__}, not callable")
    return fn


@dataclass
class Handler:
    """A loaded handler: `spec` (module:function), the function and its `params`."""

    spec: str
    fn: Callable[..., Any]
    params: Mapping[str, Any] = field(default_factory=dict)
    outputs: dict[str, str] | None = None
    """Output name -> dtype, learned on the first call (`learn_outputs`)."""

    def __call__(self, inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        try:
            result = self.fn(dict(inputs), **self.params)
        except Exception as exc:  # the handler's own failure, named, never a crash
            raise HandlerError(f"handler {self.spec} raised {type(exc).__name__}: {exc}") from exc
        return self._checked(result)

    def _checked(self, result: object) -> dict[str, np.ndarray]:
        if not isinstance(result, Mapping) or not result:
            raise HandlerError(
                f"handler {self.spec} returned {type(result).__name__}; expected a non-empty "
                "{name: numpy array}"
            )
        out: dict[str, np.ndarray] = {}
        for name, value in result.items():
            if not isinstance(name, str) or not name:
                raise HandlerError(f"handler {self.spec} returned an output named {name!r}")
            if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
                kind = type(value).__name__
                if isinstance(value, np.ndarray):
                    kind = f"array of {value.dtype}"
                raise HandlerError(
                    f"handler {self.spec}: output {name!r} is a {kind}; expected a numeric "
                    "numpy array"
                )
            out[name] = value
        if self.outputs is not None:
            got = {n: str(v.dtype) for n, v in out.items()}
            if got != self.outputs:
                raise HandlerError(
                    f"handler {self.spec}: outputs {_describe(got)}, expected "
                    f"{_describe(self.outputs)} (as on its first call)"
                )
        return out

    def learn_outputs(self, image_shape: Sequence[int]) -> dict[str, str]:
        """Call the handler once on a blank image of `image_shape` (1xHxWx3) and keep its
        outputs' names and dtypes; HandlerError if that call fails."""
        result = self({HANDLER_INPUT: np.zeros(tuple(image_shape), dtype=np.uint8)})
        self.outputs = {n: str(v.dtype) for n, v in result.items()}
        return self.outputs

    def digest(self) -> str:
        """sha256 of the spec, the params and the handler's module source (where readable)."""
        h = hashlib.sha256(f"handler:{self.spec}".encode())
        h.update(json.dumps(self.params, sort_keys=True, default=str).encode())
        for source in _sources(self.fn):
            h.update(source)
        return h.hexdigest()


def _sources(fn: Callable[..., Any]) -> list[bytes]:
    """The source of `fn`'s module and, for a module of a package, of every module beside it
    (a handler's helpers change what it computes too); none for a builtin."""
    module = sys.modules.get(getattr(fn, "__module__", "") or "")
    path = getattr(module, "__file__", None)
    if module is None or path is None:
        return []
    here = Path(path)
    files = sorted(here.parent.glob("*.py")) if getattr(module, "__package__", "") else [here]
    out = []
    for file in files:
        with suppress(OSError):
            out.append(file.name.encode() + b"\0" + file.read_bytes())
    return out


def _describe(outputs: Mapping[str, str]) -> str:
    return ", ".join(f"{n}:{d}" for n, d in sorted(outputs.items())) or "none"


def load_handler(
    spec: str, params: Mapping[str, Any] | None = None, base_dir: Path | None = None
) -> Handler:
    """Import the handler `spec` names (UserError, one line, when it cannot be used)."""
    return Handler(spec, import_handler(spec, base_dir), dict(params or {}))


def identity_model_path(image_shape: tuple[int, int, int]) -> Path:
    """The cached identity graph of a handler's image (C, H, W): input `image` uint8
    1xHxWxC, output its copy. Written on first use, renamed into place."""
    import onnx
    from onnx import TensorProto, helper

    from common.models import cache_dir
    from common.zoo_format import ZOO_OPSET

    c, h, w = image_shape
    path = cache_dir() / "handlers" / f"identity-v{IDENTITY_FORMAT}-{h}x{w}x{c}.onnx"
    if path.is_file():
        return path
    shape = [1, h, w, c]
    graph = helper.make_graph(
        [helper.make_node("Identity", [HANDLER_INPUT], [IDENTITY_OUTPUT])],
        "handler_image",
        [helper.make_tensor_value_info(HANDLER_INPUT, TensorProto.UINT8, shape)],
        [helper.make_tensor_value_info(IDENTITY_OUTPUT, TensorProto.UINT8, shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", ZOO_OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{id(model)}.tmp")
    onnx.save(model, str(tmp))
    tmp.replace(path)
    return path
