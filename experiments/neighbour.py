"""The neighbour robot of the fairness measurement, in a process of its own.

Why a process: the victim's latency is measured by a load generator in the bench's process; a
neighbour sending hundreds of frames per second from threads of that same process would hold
its GIL and delay the victim's replies on the client side, which is not what a robot on its own
computer sees. So the neighbour runs in a child started with `spawn` (never fork a process that
holds a Zenoh session) and is driven over a pipe, one phase at a time:

    ("run", fps, in_flight, seed) -> ("ready",) once a frame of it was served
    ("stop",)                     -> ("done", figures of the phase)
    ("exit",)                     -> the child closes and ends
A failure in the child is answered ("error", message).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import time
from multiprocessing.connection import Connection
from typing import Any

from common.errors import UserError

COMMAND_TIMEOUT_S = 120.0
"""How long the parent waits for the child to answer a command (its first load included)."""


def serve_commands(
    conn: Connection, config_path: str, robot: str, cut: int, codec: str, arrivals: str
) -> None:
    """The child's main: carry out the parent's commands until ("exit",)."""
    from common.config import load_fleet
    from experiments.load_generator import LoadGenerator, summarize

    cfg = load_fleet(config_path)
    try:
        while True:
            command = conn.recv()
            if command[0] == "exit":
                return
            _, fps, in_flight, seed = command
            try:
                with LoadGenerator(
                    cfg,
                    [robot],
                    fps=fps,
                    in_flight=in_flight,
                    cut=cut,
                    codec=codec,
                    seed=seed,
                    arrivals=arrivals,
                ) as gen:
                    gen.wait_served(COMMAND_TIMEOUT_S / 2)
                    started = time.monotonic()
                    conn.send(("ready",))
                    conn.recv()  # ("stop",)
                    stopped = time.monotonic()
            except UserError as exc:
                conn.send(("error", str(exc)))
                continue
            conn.send(("done", summarize(gen.records(started, stopped), stopped - started)))
    except (EOFError, KeyboardInterrupt):
        return  # the parent went away
    finally:
        conn.close()


class NeighbourProcess:
    """A child process running one emulated robot, a phase at a time (module docstring)."""

    def __init__(
        self,
        config_path: str,
        robot: str,
        *,
        cut: int = 0,
        codec: str = "raw",
        arrivals: str = "periodic",
    ) -> None:
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._proc = context.Process(
            target=serve_commands,
            args=(child, config_path, robot, cut, codec, arrivals),
            name=f"neighbour-{robot}",
            daemon=True,
        )
        self._proc.start()
        child.close()

    def __enter__(self) -> NeighbourProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pid(self) -> int:
        """The child's process id (its CPU time is read per phase)."""
        assert self._proc.pid is not None  # started in __init__
        return self._proc.pid

    def start_phase(self, fps: float | None, in_flight: int, seed: int) -> None:
        """Start sending; returns once a frame of the neighbour was served."""
        self._conn.send(("run", fps, in_flight, seed))
        self._expect("ready")

    def stop_phase(self) -> dict[str, Any]:
        """Stop sending; the phase's figures (`load_generator.summarize`)."""
        self._conn.send(("stop",))
        figures: dict[str, Any] = self._expect("done")[1]
        return figures

    def _expect(self, what: str) -> tuple[Any, ...]:
        if not self._conn.poll(COMMAND_TIMEOUT_S):
            raise UserError(f"the neighbour process did not answer within {COMMAND_TIMEOUT_S} s")
        try:
            answer: tuple[Any, ...] = self._conn.recv()
        except EOFError:
            raise UserError(
                f"the neighbour process ended (exit code {self._proc.exitcode})"
            ) from None
        if answer[0] == "error":
            raise UserError(f"neighbour: {answer[1]}")
        if answer[0] != what:
            raise UserError(f"neighbour: expected {what!r}, got {answer[0]!r}")
        return answer

    def close(self) -> None:
        """Ask the child to end; kill it if it does not."""
        with contextlib.suppress(OSError, ValueError):  # already gone
            self._conn.send(("exit",))
        self._proc.join(COMMAND_TIMEOUT_S / 10)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        self._conn.close()
