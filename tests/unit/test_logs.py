"""The daemon commands' logging setup: level names checked, lines formatted, logging restored."""

from __future__ import annotations

import io
import logging
import sys

import pytest

from common.errors import UserError
from common.logs import LOG_LEVELS, logging_to_stderr, parse_level


@pytest.mark.parametrize("name", [*LOG_LEVELS, "INFO", " Warning "])
def test_level_names_in_any_case(name: str) -> None:
    assert parse_level(name) == getattr(logging, name.strip().upper())


def test_an_unknown_level_names_the_flag_and_the_choices() -> None:
    with pytest.raises(UserError, match=r"--log-level 'loud': expected one of debug, info"):
        parse_level("loud")


def test_lines_carry_level_and_logger_then_logging_is_as_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Guards the in-process CLI tests: a command must not leave its handler on the root logger
    (it would write to a stream closed after the command)."""
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    with logging_to_stderr("debug"):
        logging.getLogger("cloudd.test").debug("hello %s", "there")
    logging.getLogger("cloudd.test").debug("after the command")
    assert " DEBUG cloudd.test: hello there" in stream.getvalue()
    assert "after the command" not in stream.getvalue()
    assert root.handlers == handlers and root.level == level


def test_a_bad_level_installs_nothing() -> None:
    root = logging.getLogger()
    handlers = list(root.handlers)
    with pytest.raises(UserError), logging_to_stderr("loud"):
        pass
    assert root.handlers == handlers
