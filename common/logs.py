"""Logging of the daemon commands (`elasticfog registry`, `cloud`, `robot`): one setup for all.

Each command logs to stderr, one line per record with a timestamp, the level and the logger's
name, at the level of `--log-level` (env ELASTICFOG_LOG_LEVEL, default info). A level that is
not one of LOG_LEVELS is a `UserError` naming it, so the command exits 2 before anything runs.
The setup is a context manager: the handler and the root level are put back when the command
ends, so running a command in-process (the CLI tests) leaves logging as it was.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

from common.errors import UserError

LOG_LEVEL_ENV = "ELASTICFOG_LOG_LEVEL"
LOG_LEVELS = ("debug", "info", "warning", "error")
DEFAULT_LOG_LEVEL = "info"
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
LOG_LEVEL_HELP = "debug, info, warning or error."


def parse_level(level: str) -> int:
    """The logging level named `level` (any case, one of LOG_LEVELS)."""
    name = level.strip().lower()
    if name not in LOG_LEVELS:
        raise UserError(f"--log-level {level!r}: expected one of {', '.join(LOG_LEVELS)}")
    return int(getattr(logging, name.upper()))


@contextlib.contextmanager
def logging_to_stderr(level: str) -> Iterator[None]:
    """Every logger's records at `level` and above on stderr while the block runs."""
    number = parse_level(level)
    root = logging.getLogger()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    previous = root.level
    root.addHandler(handler)
    root.setLevel(number)
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(previous)
