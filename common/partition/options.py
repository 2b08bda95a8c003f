"""The partitioner's options: cuts and input shapes parsed from text, and values checked up front.

Errors name the option by its parameter name (:class:`OptionError`); a front end that calls the
option something else (a CLI flag) renames it with :meth:`OptionError.naming`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from common.partition.errors import OptionError

DEFAULT_MAX_CUT_TENSORS = 2
# Joins the tensors of one cut given by name ("a+b").
CUT_SEPARATOR = "+"

InputShape = tuple[int, ...] | Mapping[str, tuple[int, ...]] | None


def parse_cuts(text: str) -> str | list[str]:
    """``auto`` or a comma-separated list of cuts (``a,b+c``) as given on the command line."""
    text = text.strip()
    if text == "auto":
        return "auto"
    items = [item.strip() for item in text.split(",")]
    if not text or any(not item for item in items):
        raise OptionError(
            "cuts", "bad {option} {text!r}: expected 'auto' or tensor names like a,b+c", text=text
        )
    return items


def parse_input_shape(text: str | None) -> InputShape:
    """``3x240x320`` (first input) or ``name=1x3x240x320,other=1x4``, as on the command line."""
    from common.zoo import parse_shape

    if text is None or not text.strip():
        return None
    if "=" not in text:
        return parse_shape(text)
    shapes: dict[str, tuple[int, ...]] = {}
    for item in text.split(","):
        name, sep, shape = item.partition("=")
        if not sep or not name.strip():
            raise OptionError(
                "input_shape", "bad {option} {text!r}: expected NAME=DxDxD,... or DxDxD", text=text
            )
        shapes[name.strip()] = parse_shape(shape)
    return shapes


def cuts_option(cuts: str | Sequence[str]) -> str | list[str]:
    """The ``cuts`` option as ``"auto"`` or a list of cuts, text parsed with :func:`parse_cuts`."""
    if isinstance(cuts, str):
        return parse_cuts(cuts)
    items = [str(c).strip() for c in cuts]
    if not items or any(not c for c in items):
        raise OptionError("cuts", "{option} must be 'auto' or a non-empty list of tensor names")
    return items


def check_max_cut_tensors(n: int) -> None:
    if not isinstance(n, int) or n < 1:
        raise OptionError("max_cut_tensors", "{option} must be a positive integer, got {n!r}", n=n)


def format_shape(shape: Sequence[int]) -> str:
    return "x".join(str(d) for d in shape)
