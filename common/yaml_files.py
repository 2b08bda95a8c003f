"""Reading the project's YAML files strictly and saying what is wrong with them in one line.

`read_yaml` reads a file with a SafeLoader that refuses duplicate keys (naming the key and both
lines: PyYAML alone keeps the last one silently) and turns every way PyYAML fails (including the
exceptions it lets escape, `YAML_ESCAPES`) into a `UserError` naming the file;
`format_validation_error` turns a pydantic `ValidationError` into `field.path: problem; ...`,
with a close match or the known keys for an unknown key. They are the only YAML reader and the
only ValidationError wording of the project's files: the fleet file (`common.config`), the
simulator's traces (`robotd.sim.trace`), the robot's phases (`robotd.emulation`), the demo's
scripts (`deploy.demo_script`), policy params and flags.
"""

from __future__ import annotations

import difflib
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Union

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from common.errors import UserError

MAX_ERRORS_SHOWN = 5
MAX_INPUT_SHOWN_CHARS = 40
"""A bad value is quoted in its error up to this many characters (a pasted blob stays short)."""
_OWN_WORDS = frozenset({"value_error", "assertion_error"})
"""Errors raised by our validators, whose message already says what was wrong with the value."""


# -- reading ---------------------------------------------------------------------------------------
YAML_ESCAPES: tuple[type[Exception], ...] = (
    ValueError,
    LookupError,
    AttributeError,
    TypeError,
    RecursionError,
)
"""What PyYAML's safe loading raises on bad text besides YAMLError (found by
tests/unit/test_fuzz_config.py): ValueError for a 13th month or a 5000-digit integer, KeyError for
`!!bool maybe`, AttributeError for `!!timestamp x`, RecursionError for thousands of nested
brackets. Every YAML loader catches these too, so bad text is a UserError, not a traceback."""


def yaml_escape_problem(exc: Exception) -> str:
    """One of YAML_ESCAPES as one line."""
    if isinstance(exc, RecursionError):
        return "nested too deeply"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (PyYAML keeps the last one silently)."""


def _no_duplicates(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    first_line: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            earlier = first_line.get(key)
        except TypeError:  # a list or map as a key: construct_mapping below names the problem
            continue
        if earlier is not None:
            mark = key_node.start_mark
            problem = f"duplicate key {key!r}, first given on line {earlier + 1}"
            raise yaml.constructor.ConstructorError(None, None, problem, mark)
        first_line[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _no_duplicates)


def read_yaml(path: Path, what: str = "", *, missing: str = "no such file") -> Any:
    """The YAML document of `path`; UserError (one line naming the file) when it cannot be read
    or is not valid YAML. `what`: how the file was given, put before its name (`--script`,
    `trace`); `missing`: what to say when the file does not exist."""
    name = f"{what} {path}" if what else str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{name}: {missing}") from None
    except IsADirectoryError:
        raise UserError(
            f"{name}: is a directory, expected a YAML file (a fleet.yaml, a trace, ...)"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{name}: cannot read: {exc}") from None
    return parse_yaml(text, name)


def parse_yaml(text: str, name: str) -> Any:
    """The YAML document in `text`, read as `read_yaml` reads a file; `name` heads the error."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise UserError(f"{name}: invalid YAML: {_yaml_problem(exc)}") from None
    except YAML_ESCAPES as exc:
        raise UserError(f"{name}: invalid YAML: {yaml_escape_problem(exc)}") from None


def _yaml_problem(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return f"{where}{problem}"


def format_validation_error(exc: ValidationError, root: type[BaseModel] | None = None) -> str:
    """Pydantic errors as one line: `field.path: problem; other.path: problem`; `root` is the
    model validated, whose fields an unknown key's message lists. The one way this project words
    a ValidationError (fleet files, traces, phases, scripts, policy params, flags)."""
    parts = []
    errors = exc.errors(include_url=False)
    for error in errors[:MAX_ERRORS_SHOWN]:
        message = validation_problem(error, root)
        path = _format_loc(tuple(error["loc"]))
        parts.append(f"{path}: {message}" if path else message)
    if len(errors) > MAX_ERRORS_SHOWN:
        parts.append(f"and {len(errors) - MAX_ERRORS_SHOWN} more")
    return "; ".join(parts)


def validation_problem(
    error: ErrorDetails, root: type[BaseModel] | None = None, *, with_input: bool = True
) -> str:
    """One pydantic error's problem without its place, on one line: an unknown key with a close
    match or the known keys, a missing key, our validators' own words, or pydantic's with the
    value it got (`Input should be greater than 0 (got -1)`; not `with_input`: without it, for a
    caller that shows the value itself)."""
    kind = error["type"]
    if kind == "extra_forbidden":
        return _unknown_key_message(tuple(error["loc"]), root)
    if kind == "missing":
        return "required key is missing"
    message = str(error["msg"]).removeprefix("Value error, ").removeprefix("Assertion failed, ")
    message = " ".join(message.split())
    got = error.get("input")
    if with_input and kind not in _OWN_WORDS and isinstance(got, (str, int, float)):
        shown = repr(got)
        if len(shown) > MAX_INPUT_SHOWN_CHARS:
            shown = shown[: MAX_INPUT_SHOWN_CHARS - 3] + "..."
        message += f" (got {shown})"
    return message


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part == "[key]":
            out += " (key)"
        else:
            # A key with a newline or a control character is quoted: the error stays one line.
            text = str(part) if str(part).isprintable() else repr(part)
            out += f".{text}" if out else text
    return out


def _unknown_key_message(loc: tuple[Any, ...], root: type[BaseModel] | None) -> str:
    known = _known_keys(loc[:-1], root) if root is not None else []
    if not known:
        return "unknown key"
    close = difflib.get_close_matches(str(loc[-1]), known, n=1, cutoff=0.6)
    if close:
        return f"unknown key; did you mean {close[0]!r}?"
    return f"unknown key; known keys here: {', '.join(known)}"


def _known_keys(loc: tuple[Any, ...], root: type[BaseModel]) -> list[str]:
    """Field names of the model found at `loc` (walking `root`'s annotations)."""
    current: Any = root
    index = 0
    while index <= len(loc):
        current = _unwrap(current)
        if isinstance(current, type) and issubclass(current, BaseModel):
            if index == len(loc):
                return list(current.model_fields)
            field = current.model_fields.get(loc[index]) if isinstance(loc[index], str) else None
            if field is None:
                return []
            current, index = field.annotation, index + 1
        elif typing.get_origin(current) in (dict, list) and index < len(loc):
            current, index = typing.get_args(current)[-1], index + 1
        else:
            return []
    return []


def _unwrap(annotation: Any) -> Any:
    """X | None -> X; Annotated[X, ...] -> X."""
    while True:
        origin = typing.get_origin(annotation)
        if origin is Annotated:
            annotation = typing.get_args(annotation)[0]
        elif origin in (Union, types.UnionType):
            members = [a for a in typing.get_args(annotation) if a is not type(None)]
            if len(members) != 1:
                return annotation
            annotation = members[0]
        else:
            return annotation
