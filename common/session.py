"""Zenoh sessions for every process of the fleet, configured in one place.

What every session gets, and why (zenoh 1.10; keys checked against the installed package):

- Multicast scouting off: machines meet through explicit endpoints (the registry's router), never
  by whoever answers on the LAN; tests on one host must not find each other's sessions either.
- Gossip scouting on: since zenoh 1.9 a router no longer relays between peers, so peers learn each
  other's listen endpoints from the router by gossip and connect directly; data then flows robot
  <-> deployment without the registry. Peers must listen on endpoints the others can reach.
- A short link lease (`transport/link/tx/lease`, 1 s by default, with 4 keep-alives per lease as
  Zenoh recommends): a frozen host or cut link is noticed (tokens dropped) in about a second
  instead of the default 10 s. A killed process is noticed at once anyway (its sockets close).
- A long wait before a blocked link is closed (`.../congestion_control/block/wait_before_close`,
  `BLOCK_WAIT_BEFORE_CLOSE_S`): a crossing of a few MB on a 1 Mbit/s uplink queues for tens of
  seconds, and with Zenoh's default (5 s) the sender then closes the whole session (its route,
  its liveliness token) instead of finishing the send. A dead link is still noticed by the lease.
- Shared memory switchable: on by default between processes of one host, but it bypasses the
  network, so it must be off when traffic shaping between namespaces is to mean anything.
- TLS file paths from fleet.yaml go to `transport/link/tls/*` (for `tls/...` endpoints).
- More reception threads (`init_runtime`): Zenoh sets SO_LINGER (10 s) on its TCP links and closes
  a dead link on one of its 2 reception ("rx") runtime threads, where `close()` blocks until the
  unsent bytes are acknowledged or the 10 s pass (zenoh issue #1101). After a pulled cable every
  link to that host holds unsent keep-alives, so one or two closing links stalled all reception
  of a process for seconds: a deployment stopped answering the registry's ctl queries and the
  robot was left computing locally. With `ZENOH_RX_WORKER_THREADS` the live links keep being
  served meanwhile.

A peer that cannot reach its connect endpoints still opens and keeps retrying in the background
(daemons must start before the registry and survive its restarts); a client fails at once, or
after `connect_timeout_s` — what a CLI query wants. Callers own the returned session and close
it (`with open_session(...) as session:`): a session still holding callbacks at interpreter exit
hangs the process.
"""

from __future__ import annotations

import json
import os
import re
import threading
from collections.abc import Sequence
from typing import Any

import zenoh

from common.config import FleetConfig, ZenohConfig
from common.errors import UserError

KEEP_ALIVES_PER_LEASE = 4
BLOCK_WAIT_BEFORE_CLOSE_S = 120.0
# Zenoh's reception runtime threads (its default is 2): each link to a host that vanished holds
# one for up to 10 s while it closes (see the module docstring), and a peer may hold two links to
# another (one each way). Idle threads cost nothing; 16 leave room for several hosts lost at once.
ZENOH_RX_WORKER_THREADS = 16
ZENOH_RUNTIME_ENV = "ZENOH_RUNTIME"
LOG_LEVEL_DEFAULT = "error"
MODES = ("peer", "client", "router")

_log_lock = threading.Lock()
_log_ready = False


def init_logging() -> None:
    """Route Zenoh's own logs (RUST_LOG if set, else errors only); once per process."""
    global _log_ready
    with _log_lock:
        if not _log_ready:
            zenoh.init_log_from_env_or(LOG_LEVEL_DEFAULT)
            _log_ready = True


def init_runtime() -> None:
    """Size Zenoh's runtime before this process opens its first session (read once, then
    fixed). A `ZENOH_RUNTIME` set by the user is left as it is."""
    os.environ.setdefault(ZENOH_RUNTIME_ENV, f"(rx: (worker_threads: {ZENOH_RX_WORKER_THREADS}))")


def _unique(items: Sequence[str]) -> list[str]:
    return list(dict.fromkeys(items))


def zenoh_settings(
    cfg: FleetConfig | None = None,
    *,
    machine: str | None = None,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    router: bool = False,
    shared_memory: bool | None = None,
    lease_ms: int | None = None,
    connect_timeout_s: float | None = None,
) -> dict[str, Any]:
    """The Zenoh settings of one process, as config key -> value (see `zenoh_config`)."""
    z = cfg.zenoh if cfg is not None else ZenohConfig()
    m = cfg.machine(machine) if cfg is not None and machine is not None else None
    if router:
        if mode not in (None, "router"):
            raise ValueError(f"router=True contradicts mode={mode!r}")
        mode = "router"
    mode = mode or z.mode
    if mode not in MODES:
        raise UserError(f"unknown Zenoh mode {mode!r}; expected one of {', '.join(MODES)}")

    if listen is None:
        if router:
            listen = cfg.registry.listen if cfg is not None else []
        else:
            listen = (m.listen if m is not None and m.listen else None) or z.listen
    if connect is None:
        if router:
            connect = []
        elif cfg is not None:
            connect = [cfg.registry.endpoint, *z.connect, *(m.connect if m is not None else [])]
        else:
            connect = list(z.connect)
    if shared_memory is None:
        override = m.shared_memory if m is not None else None
        shared_memory = z.shared_memory if override is None else override

    settings: dict[str, Any] = {
        "mode": mode,
        "connect/endpoints": _unique(connect),
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": True,
        "transport/link/tx/lease": int(lease_ms if lease_ms is not None else z.lease_ms),
        "transport/link/tx/keep_alive": KEEP_ALIVES_PER_LEASE,
        "transport/shared_memory/enabled": bool(shared_memory),
        "transport/link/tx/queue/congestion_control/block/wait_before_close": round(
            BLOCK_WAIT_BEFORE_CLOSE_S * 1e6
        ),
    }
    if listen:
        # Left unset, Zenoh listens on its own default (tcp/[::]:0 for peers).
        settings["listen/endpoints"] = _unique(listen)
    if connect_timeout_s is not None:
        settings["connect/timeout_ms"] = max(0, round(connect_timeout_s * 1000))
    tls = z.tls
    if tls.root_ca is not None:
        settings["transport/link/tls/root_ca_certificate"] = tls.root_ca
    if tls.cert is not None and tls.key is not None:
        settings["transport/link/tls/listen_certificate"] = tls.cert
        settings["transport/link/tls/listen_private_key"] = tls.key
        settings["transport/link/tls/connect_certificate"] = tls.cert
        settings["transport/link/tls/connect_private_key"] = tls.key
    if tls.mtls:
        settings["transport/link/tls/enable_mtls"] = True
    return settings


def zenoh_config(
    cfg: FleetConfig | None = None,
    *,
    machine: str | None = None,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    router: bool = False,
    shared_memory: bool | None = None,
    lease_ms: int | None = None,
    connect_timeout_s: float | None = None,
) -> zenoh.Config:
    """The Zenoh config of one process.

    Defaults come from `cfg` (fleet.yaml) and, with `machine`, that machine's overrides; explicit
    arguments win. A peer or client connects to `registry.endpoint` plus `zenoh.connect` plus the
    machine's `connect`, and listens on the machine's `listen` (else `zenoh.listen`, else Zenoh's
    default). `router=True` is the registry's embedded router, listening on `registry.listen`.
    Without `cfg` only the explicit arguments and the defaults of `ZenohConfig` apply (e.g. a CLI
    query given `--connect ENDPOINT`).
    """
    settings = zenoh_settings(
        cfg,
        machine=machine,
        mode=mode,
        listen=listen,
        connect=connect,
        router=router,
        shared_memory=shared_memory,
        lease_ms=lease_ms,
        connect_timeout_s=connect_timeout_s,
    )
    return _to_config(settings)


def _to_config(settings: dict[str, Any]) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def open_session(
    cfg: FleetConfig | None = None,
    *,
    machine: str | None = None,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    router: bool = False,
    shared_memory: bool | None = None,
    lease_ms: int | None = None,
    connect_timeout_s: float | None = None,
) -> zenoh.Session:
    """Open a session configured by `zenoh_config` (same arguments). A failure (endpoint in use,
    nothing reachable for a client) is a UserError naming the endpoints."""
    init_runtime()
    init_logging()
    settings = zenoh_settings(
        cfg,
        machine=machine,
        mode=mode,
        listen=listen,
        connect=connect,
        router=router,
        shared_memory=shared_memory,
        lease_ms=lease_ms,
        connect_timeout_s=connect_timeout_s,
    )
    try:
        return zenoh.open(_to_config(settings))
    except zenoh.ZError as exc:
        where = []
        if settings.get("listen/endpoints"):
            where.append(f"listening on {', '.join(settings['listen/endpoints'])}")
        if settings["connect/endpoints"]:
            where.append(f"connecting to {', '.join(settings['connect/endpoints'])}")
        context = f" ({'; '.join(where)})" if where else ""
        raise UserError(
            f"cannot open a Zenoh {settings['mode']} session{context}: {zenoh_error_text(exc)}"
        ) from None


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error as one readable line (without the Rust source locations)."""
    text = " ".join(str(exc).split())
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", text)
