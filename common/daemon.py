"""Daemon lifecycle shared by the registry, cloud and robot daemons.

`run()` installs signal handlers, starts up, runs the main loop until asked to stop, then shuts down
in reverse order of startup and restores the previous handlers. The first SIGINT/SIGTERM asks for a
clean stop (sessions closed explicitly: a Zenoh session still holding callbacks at interpreter exit
hangs the process); a second one forces an immediate exit, so a stuck shutdown never traps the user.
Subclasses keep `__init__` free of I/O and implement `startup`, `main_loop` and `shutdown`.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType
from typing import Any

log = logging.getLogger(__name__)

HANDLED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
FORCED_EXIT_CODE = 130


class Daemon:
    """Base class: signal handling and the startup → main loop → shutdown order."""

    name = "daemon"

    def __init__(self) -> None:
        self.should_exit = threading.Event()
        self.stop_signal: int | None = None
        self._force_exit = False
        self._previous_handlers: dict[int, Any] = {}

    # -- lifecycle hooks -------------------------------------------------------------------
    def startup(self) -> None:
        """Open sessions, declare resources. Raise to abort before the main loop."""

    def main_loop(self) -> None:
        """Run until `should_exit` is set. The default just waits."""
        self.should_exit.wait()

    def shutdown(self) -> None:
        """Release what `startup` acquired, in reverse order."""

    # -- driver ----------------------------------------------------------------------------
    def run(self) -> int:
        """Run the daemon in the calling (main) thread; returns a process exit code."""
        self._install_signal_handlers()
        try:
            self.startup()
            try:
                self.main_loop()
            finally:
                self.shutdown()
        finally:
            self._restore_signal_handlers()
        return 0

    def stop(self) -> None:
        """Ask the main loop to finish (thread-safe)."""
        self.should_exit.set()

    def _handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if self.should_exit.is_set() and sig == signal.SIGINT:
            # Second Ctrl-C: the user wants out now, even if shutdown is stuck.
            self._force_exit = True
            log.warning("%s: forced exit", self.name)
            os._exit(FORCED_EXIT_CODE)
        self.stop_signal = sig
        log.info("%s: received %s, stopping", self.name, signal.Signals(sig).name)
        self.should_exit.set()

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # signals can only be handled in the main thread (e.g. daemons run in tests)
        for sig in HANDLED_SIGNALS:
            self._previous_handlers[sig] = signal.signal(sig, self._handle_exit)

    def _restore_signal_handlers(self) -> None:
        for sig, handler in self._previous_handlers.items():
            signal.signal(sig, handler)
        self._previous_handlers.clear()
