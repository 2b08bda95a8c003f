"""`elasticfog results`: follow one robot's results, a line (or a JSON object) per applied frame.

    elasticfog results --config fleet.yaml --robot robot-1 [--count N] [--json]

Subscribes to `ef/<fleet>/out/<robot>` through a Zenoh client session to the fleet's router (the
registry's endpoint; `robotd.results.client.RobotClient`) and prints each `FrameResultMessage`:
frame, capture stamp, who served it, the action, the end-to-end latency and each output's shape,
with the top-5 indices and values of a 1-D or N×C output (per row). `--json`: one object per line
(`result_json`; each names its `service`, and `--service NAME` keeps one service's). Ends after
`--count` results, after `--timeout` seconds without one, or on Ctrl-C/SIGTERM (exit 0). An
unreachable fleet is one line on stderr and exit code 2.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from common.errors import UserError
from common.logs import DEFAULT_LOG_LEVEL, LOG_LEVEL_ENV, LOG_LEVEL_HELP, logging_to_stderr

if TYPE_CHECKING:
    import numpy as np

    from robotd.results.client import Result, RobotClient

TOP_K = 5
# How often the wait for a result looks at the stop flag.
POLL_S = 0.2


def register(app: typer.Typer) -> None:
    """Add `results` to the root app."""
    app.command("results", help="Follow a robot's results: one line per applied frame.")(
        results_command
    )


def results_command(
    config: Path = typer.Option(..., "--config", help="The fleet file (fleet.yaml)."),
    robot: str = typer.Option(..., "--robot", help="The robot whose results to follow."),
    count: int | None = typer.Option(None, "--count", min=1, help="Stop after N results."),
    timeout: float | None = typer.Option(
        None, "--timeout", help="Stop after this many seconds without a result (default: never)."
    ),
    service: str | None = typer.Option(
        None,
        "--service",
        help="Only the results of this service (a robot using several publishes them all).",
    ),
    json_out: bool = typer.Option(False, "--json", help="One JSON object per result."),
    log_level: str = typer.Option(
        DEFAULT_LOG_LEVEL, "--log-level", envvar=LOG_LEVEL_ENV, help=LOG_LEVEL_HELP
    ),
) -> None:
    """Print each applied frame's result of ROBOT until --count, --timeout or Ctrl-C."""
    from robotd.results.client import RobotClient

    stop = threading.Event()
    try:
        with logging_to_stderr(log_level), _stop_on_signals(stop):
            if timeout is not None and not timeout > 0:
                raise UserError(f"--timeout must be a positive number, got {timeout}")
            with RobotClient(config, robot) as client:
                if service is not None:
                    client.config.service_for(service)  # UserError naming the services
                # On stderr: what is followed, once the subscriber is declared.
                of = "" if service is None else f" (service {service})"
                typer.echo(f"following {client.out_key}{of}", err=True)
                results = (
                    r
                    for r in _follow(client, stop, timeout)
                    if service is None or _service_of(client, r) == service
                )
                for n, result in enumerate(results, start=1):
                    line = json.dumps(result_json(result)) if json_out else result_line(result)
                    typer.echo(line)
                    sys.stdout.flush()
                    if count is not None and n >= count:
                        break
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    raise typer.Exit(0)


def _service_of(client: RobotClient, result: Result) -> str:
    """The service a result is for (a robot of a one-service fleet names none)."""
    return client.config.service_for(result.message.service)


def _follow(client: RobotClient, stop: threading.Event, timeout: float | None) -> Iterator[Result]:
    """Results until `stop` is set or none came within `timeout` seconds."""
    quiet_since = time.monotonic()
    while not stop.is_set():  # bounded by the stop flag (signals) or the timeout
        got = False
        for result in client.results(timeout=POLL_S):
            got = True
            yield result
            if stop.is_set():
                return
        now = time.monotonic()
        if got:
            quiet_since = now
        elif timeout is not None and now - quiet_since >= timeout:
            return


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set `stop` (the loop ends, the session closes); handlers restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handle(signum: int, frame: object) -> None:
        stop.set()

    for sig in previous:
        signal.signal(sig, handle)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def top_k(array: np.ndarray, k: int = TOP_K) -> list[list[tuple[int, float]]] | None:
    """The top-`k` (index, value) pairs of a 1-D output, or of each row of an N×C one, largest
    first; None for other shapes."""
    import numpy as np

    if array.ndim not in (1, 2) or array.size == 0 or array.dtype.kind not in "fiub":
        return None
    rows = array.reshape(1, -1) if array.ndim == 1 else array
    out = []
    for row in rows:
        values = row.astype(np.float64)
        k_row = min(k, values.size)
        top = np.argpartition(-values, k_row - 1)[:k_row]
        top = top[np.argsort(-values[top], kind="stable")]
        out.append([(int(i), float(values[i])) for i in top])
    return out


def _stamp_text(stamp_ns: int) -> str:
    moment = datetime.fromtimestamp(stamp_ns / 1e9, tz=timezone.utc)
    return moment.strftime("%H:%M:%S.%f")[:-3]


def result_line(result: Result) -> str:
    """One line for a person."""
    m = result.message
    served = m.served_by.value + (f" ({m.deployment})" if m.deployment else "")
    parts = [
        *([f"service {m.service}"] if m.service is not None else []),
        f"frame {m.frame}",
        f"stamp {m.stamp_ns} ({_stamp_text(m.stamp_ns)})",
        f"served_by {served}",
        f"action {m.action}",
        f"latency {m.latency_s * 1000:.1f} ms",
    ]
    for name, array in result.outputs.items():
        text = f"{name} {list(array.shape)}"
        top = top_k(array)
        if top is not None:
            rows = [" ".join(f"{i}:{v:.4g}" for i, v in row) for row in top]
            text += " top5 " + " | ".join(rows)
        parts.append(text)
    return "  ".join(parts)


def result_json(result: Result) -> dict[str, Any]:
    """The JSON object of one result: the message's fields, and per output its dtype, shape,
    codec and top-5 rows (null unless 1-D or N×C)."""
    m = result.message
    return {
        "robot": m.robot,
        "service": m.service,
        "frame": m.frame,
        "stamp_ns": m.stamp_ns,
        "served_by": m.served_by.value,
        "deployment": m.deployment,
        "action": m.action,
        "cut": m.cut,
        "codec": m.codec,
        "fallback": m.fallback,
        "latency_s": m.latency_s,
        "published_ns": m.published_ns,
        "received_ns": result.received_ns,
        "outputs": {
            name: {
                "dtype": array.dtype.name,
                "shape": list(array.shape),
                "codec": m.outputs[name].codec,
                "top5": top_k(array),
            }
            for name, array in result.outputs.items()
        },
    }
