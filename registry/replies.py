"""How the registry reads a query and answers it, for every queryable it declares.

A request is decoded strictly (`decode_query`: at most `registry.max_request_bytes`, 64 KiB by
default, checked on the length before unpacking; the expected message type only), so bad input
raises a `WireError` naming the problem; the daemon's guarded callbacks answer it
with `error_payload`, the matching `ErrorReply`. `answer` sends the replies and finalizes the
query at once (a querier waits for the final reply), tolerating a querier that went away.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from common.session import zenoh_error_text
from common.wire import ErrorCode, ErrorReply, Message, WireError, decode, error_reply
from common.wire.errors import PayloadTooLarge
from registry.refusals import Refusals

log = logging.getLogger(__name__)

INTERNAL_REASON = "internal error; see the registry log"
LIMIT_FIELD = "registry.max_request_bytes"


class UnknownService(WireError):
    """A request or publication naming a service this fleet does not serve: refused (an error
    reply, or a dropped publication), the reason naming the fleet's services."""

    code = ErrorCode.UNKNOWN_SERVICE


def unknown_service(name: str, services: Iterable[str]) -> UnknownService:
    """The refusal of `name`, listing the fleet's services."""
    return UnknownService(f"unknown service {name!r}; this fleet's services: {', '.join(services)}")


def check_service(name: str | None, services: Iterable[str]) -> None:
    """UnknownService unless `name` is None (a peer of a one-service fleet: the first service)
    or one of `services`."""
    known = tuple(services)
    if name is not None and name not in known:
        raise unknown_service(name, known)


def check_size(data: bytes, max_bytes: int, what: str) -> None:
    """PayloadTooLarge (`too_large`) naming the limit and the fleet field that sets it when
    `data` is over `max_bytes`: checked on the length, before any unpacking."""
    if len(data) > max_bytes:
        raise PayloadTooLarge(
            f"{what} of {len(data)} bytes exceeds the registry's limit of {max_bytes} bytes "
            f"({LIMIT_FIELD})"
        )


def decode_query(
    query: zenoh.Query, kind: type[Message], *, max_bytes: int, empty_ok: bool = False
) -> Any:
    """The query's payload as a `kind` (an empty one as `kind()` when `empty_ok`); a
    WireError naming the problem otherwise (`too_large` over `max_bytes`)."""
    payload = query.payload
    data = payload.to_bytes() if payload is not None else b""
    if not data and empty_ok:
        return kind()
    check_size(data, max_bytes, f"{kind.TYPE} request")
    return decode(data, expect=kind, max_bytes=max_bytes)


def refusal(reason: str) -> bytes:
    """A well-formed request the registry will not act on."""
    return ErrorReply.make(ErrorCode.REFUSED, reason).to_wire()


def error_payload(exc: Exception) -> bytes:
    """The reply to a request that failed: bad input names its problem, anything else is an
    internal error (the log has the traceback)."""
    if isinstance(exc, WireError):
        return error_reply(exc)
    return ErrorReply.make(ErrorCode.INTERNAL, INTERNAL_REASON).to_wire()


def answer(query: zenoh.Query, *replies: tuple[str, bytes]) -> None:
    """Send each (key, payload) reply, then finalize the query; a querier that went away (its
    timeout passed, its session closed) is no error."""
    with query:
        for key, payload in replies:
            try:
                query.reply(key, payload)
            except zenoh.ZError as exc:
                log.debug("cannot reply on %s: %s", key, zenoh_error_text(exc))


def answer_error(
    refusals: Refusals,
    name: str,
    reply_key: Callable[[zenoh.Query], str],
    query: zenoh.Query,
    exc: Exception,
) -> None:
    """Answer a query whose callback failed (the daemon's guard has logged why) on
    `reply_key(query)`, and count it in `refusals` under `name`."""
    refusals.count(name, exc.code if isinstance(exc, WireError) else ErrorCode.INTERNAL)
    answer(query, (reply_key(query), error_payload(exc)))
