"""The bench's eyes inside the testbed: a Zenoh peer on a host of its own, driven over stdin/stdout.

The testbed's addresses exist only inside its namespaces, so the process running an experiment
(in the machine's own namespace) cannot open a Zenoh session to the fleet itself, and it must not
move into a namespace either (Zenoh's threads would stay there). It starts this helper on the
`bench` host instead (`python -m experiments.observer --config F --listen EP`) and
talks to it with one JSON object per line:

    -> {"id": 1, "op": "wait_tokens", "keys": [...], "present": true, "timeout_s": 30}
    <- {"id": 1, "ok": true}
    -> {"id": 2, "op": "view", "name": "deployments"}
    <- {"id": 2, "ok": true, "rows": [{...}, ...]}
    -> {"id": 3, "op": "fault", "deployment": "edge-1", "delay_ms": 400, "drop": 0, "stall": false}
    <- {"id": 3, "ok": true}
    -> {"id": 4, "op": "quit"}

A failed request answers `{"id": N, "ok": false, "error": "one line"}`; the helper keeps running.
It prints `{"event": "ready"}` once its session is open. End of input, `quit`, SIGINT or SIGTERM
close the session and exit. Its traffic (liveliness, registry views, ctl) is small and crosses
only the bench host's own link and the link of whoever it asks. In a TLS fleet it shows the
registry's certificate (`deploy.local_fleet.observer_identity`), which carries the bench host's
address.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from deploy.local_fleet import LocalFleet, observer_identity
from deploy.readiness import TokenWatch


class _NamespaceObserver(LocalFleet):
    """`LocalFleet`'s watching half (tokens, views, probe, ctl), listening on the testbed
    address it is given instead of loopback, and starting no daemon."""

    def __init__(self, config: Path, workdir: Path, listen: Sequence[str]) -> None:
        super().__init__(config, workdir)
        self._listen = list(listen)

    @property
    def session(self) -> Any:
        if self._session is None:
            from common.session import open_session

            self._session = open_session(
                self.cfg, identity=observer_identity(self.cfg), listen=self._listen
            )
            self._tokens = TokenWatch(self._session, self.fleet)
        return self._session


class _Server:
    def __init__(self, observer: _NamespaceObserver) -> None:
        self.observer = observer
        self._out = threading.Lock()

    def emit(self, obj: dict[str, Any]) -> None:
        with self._out:
            sys.stdout.write(json.dumps(obj) + "\n")
            sys.stdout.flush()

    def handle(self, request: dict[str, Any]) -> dict[str, Any] | None:
        """The reply to one request (None for quit)."""
        from common.wire.codec import to_jsonable

        op = request.get("op")
        obs = self.observer
        if op == "quit":
            return None
        if op == "wait_tokens":
            obs.tokens.wait_for(
                list(request["keys"]),
                timeout_s=float(request.get("timeout_s", 30.0)),
                present=bool(request.get("present", True)),
            )
            return {"ok": True}
        if op == "alive":
            return {"ok": True, "keys": sorted(obs.tokens.alive)}
        if op == "view":
            rows = obs.view(str(request["name"]), timeout_s=float(request.get("timeout_s", 2.0)))
            return {"ok": True, "rows": [to_jsonable(r) for r in rows]}
        if op == "fault":
            obs.set_fault(
                str(request["deployment"]),
                delay_ms=float(request.get("delay_ms", 0.0)),
                drop=float(request.get("drop", 0.0)),
                stall=bool(request.get("stall", False)),
            )
            return {"ok": True}
        if op == "probe":
            reply = obs.probe(str(request["deployment"]))
            return {"ok": True, "reply": to_jsonable(reply)}
        return {"ok": False, "error": f"unknown op {op!r}"}

    def serve(self) -> None:
        _ = self.observer.session  # open it now: "ready" means the session is up
        self.emit({"event": "ready"})
        for line in sys.stdin:
            if not line.strip():
                continue
            request: dict[str, Any] = {}
            try:
                request = json.loads(line)
                reply = self.handle(request)
            except Exception as exc:  # one bad request must not end the helper
                reply = {"ok": False, "error": " ".join(str(exc).split()) or type(exc).__name__}
            if reply is None:
                return
            self.emit({"id": request.get("id"), **reply})


def _raise_interrupt(sig: int, frame: object) -> None:
    raise KeyboardInterrupt(signal.Signals(sig).name)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, type=Path, help="The run's fleet.yaml.")
    parser.add_argument("--listen", required=True, action="append", help="Zenoh endpoint.")
    parser.add_argument("--workdir", type=Path, default=Path("."), help="Unused scratch dir.")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    observer = _NamespaceObserver(args.config, args.workdir, args.listen)
    try:
        _Server(observer).serve()
    except KeyboardInterrupt:
        pass
    finally:
        observer.close()  # a session holding callbacks at exit would hang the process
    return 0


if __name__ == "__main__":
    sys.exit(main())
