"""Daemon lifecycle shared by the registry, cloud and robot daemons.

`run()` captures SIGINT/SIGTERM, starts up, runs the main loop until asked to stop, then shuts
down and restores the previous handlers. Shutdown runs also when startup failed half-way, so
whatever startup had made by then is released. The first signal asks for a clean stop (sessions
closed explicitly: a Zenoh session still holding callbacks at interpreter exit hangs the
process); a second Ctrl-C forces an immediate exit, so a stuck shutdown never traps the user.
Subclasses keep `__init__` free of I/O and implement `startup` and `main_loop`. `ready` is set
between the two (the token is up: the fleet may use the daemon) and cleared when shutdown begins,
the same in all three daemons.

The lifecycle owns resources. Everything startup makes is handed to the daemon as it is made:
`hold(cm, what)` enters a context manager (a session, a subscriber, a queryable, a publisher, a
file, a SplitModel), `on_release(fn, what=...)` registers a release step (join a thread, stop a
pool), and `announce(token)` takes the liveliness token. Shutdown releases the token first (the
fleet stops counting on this process at once, instead of noticing failures later), then
everything else in reverse order of registration; one release that fails is logged and the rest
still run. It all lives in `contextlib.ExitStack`s, so there is no per-daemon cleanup list and no
chain of None checks, and releasing twice is harmless.

Zenoh calls callbacks on its own threads and an exception raised into it is lost or worse:
`guarded(callback)` wraps every one. Bad input (`WireError`) becomes one throttled WARNING line,
anything else a throttled ERROR with its traceback; both go through the daemon's one
`ThrottledLog` (`self.throttled`), which daemons use for their own bad-input lines too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack
from types import FrameType, TracebackType
from typing import Any, TypeVar

import zenoh

from common.throttled_log import ThrottledLog
from common.wire import WireError

log = logging.getLogger(__name__)

HANDLED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
FORCED_EXIT_CODE = 130

T = TypeVar("T")
_ExitFn = Callable[
    [type[BaseException] | None, BaseException | None, TracebackType | None], bool | None
]


class Daemon:
    """Base class: signal handling, the startup → main loop → shutdown order, and the resources
    startup declared."""

    name = "daemon"

    def __init__(self) -> None:
        self.should_exit = threading.Event()
        # Set once startup has finished (the token is up: the fleet may use us), cleared when
        # shutdown begins; what tests and embedders wait on instead of sleeping.
        self.ready = threading.Event()
        # Set when shutdown begins: callbacks still in flight can tell an error from a teardown.
        self.closing = threading.Event()
        self.stop_signal: int | None = None
        # Log lines of callbacks and bad input: at most a burst per window (see ThrottledLog).
        self.throttled = ThrottledLog(
            logging.getLogger(type(self).__module__), label=lambda: self.name
        )
        self._previous_handlers: dict[int, Any] = {}
        self._tokens = ExitStack()
        self._resources = ExitStack()

    # -- lifecycle hooks -------------------------------------------------------------------
    def startup(self) -> None:
        """Open sessions, declare resources (`hold`, `on_release`, `announce`). Raise to abort:
        what was declared until then is released by `shutdown`."""

    def main_loop(self) -> None:
        """Run until `should_exit` is set. The default just waits."""
        self.should_exit.wait()

    def shutdown(self) -> None:
        """Release the liveliness token, then every other resource in reverse order of
        declaration. A subclass that has more to do does it, then calls this."""
        self.ready.clear()
        self.closing.set()
        self._tokens.close()
        self._resources.close()

    # -- resources -------------------------------------------------------------------------
    def hold(self, resource: AbstractContextManager[T], what: str) -> T:
        """Enter `resource` and keep it until shutdown exits it; returns what it entered as."""
        entered = resource.__enter__()
        self._resources.push(self._tolerant(what, resource.__exit__))
        return entered

    def on_release(
        self, fn: Callable[..., object], *args: object, what: str, **kwargs: object
    ) -> None:
        """Call `fn(*args, **kwargs)` at shutdown, in reverse order with everything held."""

        def release(*_exc: object) -> None:
            fn(*args, **kwargs)

        self._resources.push(self._tolerant(what, release))

    def announce(self, token: zenoh.LivelinessToken) -> zenoh.LivelinessToken:
        """Keep the liveliness `token`: released before anything else at shutdown. Declare it
        last in startup: from then on the fleet may use us."""
        self._tokens.push(self._tolerant("liveliness token", token.__exit__))
        return token

    def _tolerant(self, what: str, exit_fn: Callable[..., Any]) -> _ExitFn:
        """`exit_fn` as an ExitStack entry that logs its failure instead of raising it, so one
        resource that cannot be released does not keep the others."""

        def exit_(
            exc_type: type[BaseException] | None,
            exc: BaseException | None,
            tb: TracebackType | None,
        ) -> bool:
            try:
                exit_fn(exc_type, exc, tb)
            except Exception as error:
                log.warning("%s: releasing the %s failed: %s", self.name, what, error)
            return False

        return exit_

    # -- callbacks -------------------------------------------------------------------------
    def guarded(
        self,
        callback: Callable[[T], None],
        *,
        what: str | None = None,
        on_error: Callable[[T, Exception], None] | None = None,
        drop_when_closing: bool = False,
    ) -> Callable[[T], None]:
        """`callback` as a Zenoh callback that never raises.

        A `WireError` escaping it is bad input: one throttled WARNING naming `what` (default:
        the callback's name). Any other exception is a bug: a throttled ERROR with the
        traceback. Once shutdown has begun either is only logged at DEBUG (resources are going
        away under the callback). `on_error(arg, exc)` then runs, e.g. to answer a query with
        an error reply. `drop_when_closing`: ignore calls once shutdown has begun.
        """
        where = what or _callback_name(callback)

        def call(arg: T) -> None:
            if drop_when_closing and self.closing.is_set():
                return
            try:
                callback(arg)
            except Exception as exc:
                if self.closing.is_set():
                    log.debug("%s: error in %s while closing: %s", self.name, where, exc)
                elif isinstance(exc, WireError):
                    self.throttled.warning("%s: bad input on %s: %s", self.name, where, exc.reason)
                else:
                    self.throttled.error(
                        "%s: unexpected error in %s", self.name, where, exc_info=True
                    )
                if on_error is not None:
                    try:
                        on_error(arg, exc)
                    except Exception as again:
                        log.debug("%s: error handler of %s failed: %s", self.name, where, again)

        return call

    # -- driver ----------------------------------------------------------------------------
    def run(self) -> int:
        """Run the daemon in the calling (main) thread; returns a process exit code."""
        with self._captured_signals():
            try:
                self.startup()
                self.ready.set()
                self.main_loop()
            finally:
                self.shutdown()
        return 0

    def stop(self) -> None:
        """Ask the main loop to finish (thread-safe)."""
        self.should_exit.set()

    def _handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if self.should_exit.is_set() and sig == signal.SIGINT:
            # Second Ctrl-C: the user wants out now, even if shutdown is stuck.
            log.warning("%s: forced exit", self.name)
            os._exit(FORCED_EXIT_CODE)
        self.stop_signal = sig
        log.info("%s: received %s, stopping", self.name, signal.Signals(sig).name)
        self.should_exit.set()

    @contextlib.contextmanager
    def _captured_signals(self) -> Iterator[None]:
        """Our handlers while the daemon runs, the previous ones restored afterwards."""
        if threading.current_thread() is not threading.main_thread():
            yield  # signals can only be handled in the main thread (e.g. daemons run in tests)
            return
        for sig in HANDLED_SIGNALS:
            self._previous_handlers[sig] = signal.signal(sig, self._handle_exit)
        try:
            yield
        finally:
            for signum, handler in self._previous_handlers.items():
                signal.signal(signum, handler)
            self._previous_handlers.clear()


def _callback_name(callback: Callable[..., Any]) -> str:
    func = getattr(callback, "func", callback)  # a functools.partial names its function
    return str(getattr(func, "__name__", None) or repr(callback))
