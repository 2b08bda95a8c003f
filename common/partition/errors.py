"""The partitioner's errors: a tensor set that is not a cut, a bad option value, and
onnxruntime's errors made readable on one line."""

from __future__ import annotations

import re
from typing import Any

from common.errors import UserError

_MAX_REASON_CHARS = 300


class CutError(Exception):
    """A tensor set is not a usable cut; the message says why."""


class OptionError(UserError):
    """A bad value of one of the partitioner's options.

    ``option`` is the parameter's name (``cuts``, ``input_shape``, ``max_cut_tensors``,
    ``out_dir``), and the message is ``template`` filled with ``values`` and ``{option}``: the
    library's own message names the parameter, and a front end names it its own way (a CLI flag)
    with :meth:`naming`, so the library never needs to know the front end's flags.
    """

    def __init__(self, option: str, template: str, **values: object) -> None:
        self.option = option
        self.template = template
        self.values = values
        super().__init__(self.naming(option))

    def naming(self, name: str) -> str:
        """The message with the option called ``name`` (e.g. ``--input-shape``)."""
        return self.template.format(option=name, **self.values)

    def __reduce__(self) -> tuple[Any, ...]:
        # Exceptions pickle as cls(*args); this one is made from its template, not its message.
        return (_option_error, (self.option, self.template, self.values))


def _option_error(option: str, template: str, values: dict[str, object]) -> OptionError:
    return OptionError(option, template, **values)


def ort_reason(exc: BaseException) -> str:
    """onnxruntime's error without its status prefix and C++ source location, on one line."""
    text = one_line(exc, limit=2000)
    text = re.sub(r"^\[ONNXRuntimeError\] : \d+ : \w+ : ", "", text)
    if text.startswith("/onnxruntime_src/") or text.startswith("onnxruntime/"):
        # "/path/file.cc:256 Type fn(args...) Message" -> "Message"
        m = re.search(r"\) (?=[A-Z\[])", text)
        if m:
            text = text[m.end() :]
    opset = re.search(r"Opset (\d+) is under development.*domain (\S+) is till opset (\d+)", text)
    if opset:
        used, domain, top = opset.groups()
        return f"the model uses opset {used} of {domain}; this onnxruntime supports up to {top}"
    return text[:_MAX_REASON_CHARS]


def one_line(exc: BaseException, limit: int = _MAX_REASON_CHARS) -> str:
    """An exception's message on one line, cut at ``limit`` characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:limit]
