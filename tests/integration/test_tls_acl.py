"""Mutual TLS and the generated access control with real Zenoh sessions on loopback.

A fleet written by `elasticfog init --tls` (its certificates, its fleet file); sessions opened
through `common.session` as the registry's router, edge-1, robot-1, robot-2 and the CLI, each
with its own certificate. Each forbidden action fails (no reply, a declaration nobody routes to,
a publication nobody receives) and each allowed one works; a client without a certificate, or
with one from another CA, cannot connect, and the preflight names the reason within seconds.

Forbidden things are shown absent after a barrier, never after a sleep: robot-2 does the
forbidden thing, then an allowed one on the same link (Zenoh keeps a link's messages in order),
and once the allowed one has arrived the forbidden one would have too.
"""

from __future__ import annotations

import shutil
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common import keys
from common.certs import CertError, SanSpec, init_fleet_certs, issue
from common.config import FleetConfig, TlsConfig, load_fleet
from common.init_cli import write_fleet
from common.session import open_session, zenoh_config
from common.tls_preflight import probe_endpoint
from deploy.readiness import wait_until
from tests.integration.conftest import WAIT_TIMEOUT_S, find_free_port

QUERY_TIMEOUT_S = 1.0
FAILURE_NAMED_WITHIN_S = 5.0


@dataclass
class TlsFleet:
    cfg: FleetConfig
    certs: Path
    router: zenoh.Session
    edge: zenoh.Session
    robot1: zenoh.Session
    robot2: zenoh.Session
    ctl_calls: list[str]
    svc_calls: list[str]

    @property
    def fleet(self) -> str:
        return self.cfg.fleet

    @property
    def endpoint(self) -> str:
        return self.cfg.registry.endpoint


def _answer(calls: list[str], name: str) -> Callable[[zenoh.Query], None]:
    def on_query(query: zenoh.Query) -> None:
        calls.append(str(query.key_expr))
        query.reply(query.key_expr, name.encode())

    return on_query


def _wait(predicate: Callable[[], Any], what: str, timeout_s: float = WAIT_TIMEOUT_S) -> Any:
    """Poll `predicate` (each call is itself bounded: a query with a timeout) until it holds."""
    return wait_until(predicate, timeout_s=timeout_s, what=what)


def _ok_replies(session: zenoh.Session, key: str, **kwargs: Any) -> list[bytes]:
    replies = session.get(key, timeout=QUERY_TIMEOUT_S, **kwargs)
    return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


def _answers(session: zenoh.Session, key: str, **kwargs: Any) -> list[bytes]:
    """An allowed query's replies, asked again while none come: for a moment after a client's
    routes change, zenoh may end its query at once with no reply and without sending it
    (eclipse-zenoh/zenoh#2767; seen here on a loaded host right after the fixture's first
    answer). A forbidden query is asked once, after an allowed one on the same link."""
    return _wait(lambda: _ok_replies(session, key, **kwargs) or None, f"an answer on {key}")


@pytest.fixture(scope="module")
def fleet_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("tls-fleet")
    return write_fleet(
        directory,
        port=find_free_port(),
        fleet=f"tls-{uuid.uuid4().hex[:8]}",
        robots=2,
        tls=True,
    )


@pytest.fixture
def tls(fleet_file: Path) -> Iterator[TlsFleet]:
    cfg = load_fleet(fleet_file)
    fleet, service = cfg.fleet, cfg.service
    opened: list[zenoh.Session] = []

    def session(**kwargs: Any) -> zenoh.Session:
        s = open_session(cfg, **kwargs)
        opened.append(s)
        return s

    ctl_calls: list[str] = []
    svc_calls: list[str] = []
    try:
        router = session(router=True)
        router.declare_queryable(keys.rib_all(fleet), _answer([], "rib"))
        edge = session(machine="edge-1")
        edge.declare_queryable(
            keys.svc_infer_all(fleet, service), _answer(svc_calls, "edge-1"), complete=True
        )
        edge.declare_queryable(keys.dep_ctl(fleet, "edge-1"), _answer(ctl_calls, "ctl"))
        edge.declare_queryable(keys.dep_probe(fleet, "edge-1"), _answer([], "probe"))
        robot1 = session(machine="robot-1")
        robot2 = session(machine="robot-2")
        for s, robot in ((robot1, "robot-1"), (robot2, "robot-2")):
            _answers(s, keys.svc_infer(fleet, service, robot))
        svc_calls.clear()
        yield TlsFleet(
            cfg, fleet_file.parent / "certs", router, edge, robot1, robot2, ctl_calls, svc_calls
        )
    finally:
        for s in reversed(opened):
            s.close()


def _barrier_token(t: TlsFleet, observer: zenoh.Session) -> None:
    """robot-2 declares its own (allowed) token; wait until `observer` sees it."""
    key = keys.alive_robot(t.fleet, "robot-2")
    token = t.robot2.liveliness().declare_token(key)
    try:
        _wait(
            lambda: any(r.ok is not None for r in observer.liveliness().get(key, timeout=0.5)),
            f"{key} seen by the observer",
        )
    finally:
        token.undeclare()


# -- robot-2 against robot-1's keys ----------------------------------------------------------------
def test_robot2_gets_no_reply_from_robot1s_service_key(tls: TlsFleet) -> None:
    svc = tls.cfg.service
    assert _answers(tls.robot1, keys.svc_infer(tls.fleet, svc, "robot-1")) == [b"edge-1"]
    assert _answers(tls.robot2, keys.svc_infer(tls.fleet, svc, "robot-2")) == [b"edge-1"]
    calls_before = len(tls.svc_calls)
    assert _ok_replies(tls.robot2, keys.svc_infer(tls.fleet, svc, "robot-1")) == []
    # Refused on the way in: edge-1's handler never ran for it.
    assert tls.svc_calls[calls_before:] == []


def test_robot2_cannot_declare_a_queryable_that_gets_queries(tls: TlsFleet) -> None:
    svc = tls.cfg.service
    stolen: list[str] = []
    on_query = _answer(stolen, "robot-2")
    robot1_key = keys.svc_infer(tls.fleet, svc, "robot-1")
    tls.robot2.declare_queryable(robot1_key, on_query, complete=True)
    tls.robot2.declare_queryable(keys.svc_infer_all(tls.fleet, svc), on_query, complete=True)
    tls.robot2.declare_queryable(f"{keys.prefix(tls.fleet)}/svc/**", on_query)
    _barrier_token(tls, tls.robot1)
    # Every queryable robot-1's session routes to answers; robot-2's are not among them.
    for _ in range(3):
        replies = _answers(tls.robot1, robot1_key, target=zenoh.QueryTarget.ALL)
        assert replies == [b"edge-1"]
    assert stolen == []


def test_robot2_cannot_change_a_deployments_state(tls: TlsFleet) -> None:
    ctl = keys.dep_ctl(tls.fleet, "edge-1")
    assert _ok_replies(tls.robot2, ctl, payload=b"drain") == []
    assert tls.ctl_calls == []
    assert _answers(tls.router, ctl, payload=b"status") == [b"ctl"]  # the registry may
    assert tls.ctl_calls == [ctl]


def test_robot2_cannot_publish_robot1s_telemetry(tls: TlsFleet) -> None:
    got: list[str] = []
    arrived = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(str(sample.key_expr))
        if str(sample.key_expr) == keys.tele(tls.fleet, "robot-2"):
            arrived.set()

    tls.router.declare_subscriber(keys.tele_all(tls.fleet), on_sample)
    _barrier_token(tls, tls.router)  # the subscriber is known to robot-2 by now too

    def publish() -> bool:
        tls.robot2.put(keys.tele(tls.fleet, "robot-1"), b"forged")
        tls.robot2.put(keys.tele(tls.fleet, "robot-2"), b"own")
        return arrived.wait(0.5)

    _wait(publish, "robot-2's own telemetry at the registry")
    assert keys.tele(tls.fleet, "robot-1") not in got


def test_robot2_cannot_follow_robot1s_route(tls: TlsFleet) -> None:
    got: list[str] = []
    own = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(str(sample.key_expr))
        if str(sample.key_expr) == keys.route(tls.fleet, "robot-2"):
            own.set()

    tls.robot2.declare_subscriber(keys.route(tls.fleet, "robot-1"), on_sample)
    tls.robot2.declare_subscriber(keys.route(tls.fleet, "robot-2"), on_sample)
    _barrier_token(tls, tls.router)

    def publish() -> bool:
        tls.router.put(keys.route(tls.fleet, "robot-1"), b"r1")
        tls.router.put(keys.route(tls.fleet, "robot-2"), b"r2")
        return own.wait(0.5)

    _wait(publish, "robot-2's own route")
    assert keys.route(tls.fleet, "robot-1") not in got


def test_robot2_cannot_declare_another_hosts_token(tls: TlsFleet) -> None:
    forged = [
        tls.robot2.liveliness().declare_token(keys.alive_robot(tls.fleet, "robot-1")),
        tls.robot2.liveliness().declare_token(keys.alive_deployment(tls.fleet, "edge-9")),
    ]
    _barrier_token(tls, tls.router)
    alive = {
        str(r.ok.key_expr)
        for r in tls.router.liveliness().get(keys.alive_all(tls.fleet), timeout=QUERY_TIMEOUT_S)
        if r.ok is not None
    }
    assert keys.alive_deployment(tls.fleet, "edge-9") not in alive
    assert keys.alive_robot(tls.fleet, "robot-1") not in alive
    for token in forged:
        token.undeclare()


# -- the CLI ---------------------------------------------------------------------------------------
def test_the_cli_certificate_reads_views_not_ctl(tls: TlsFleet) -> None:
    with open_session(tls.cfg, identity="cli", mode="client", listen=[]) as cli:
        assert _answers(cli, keys.rib_routes(tls.fleet)) == [b"rib"]
        assert _ok_replies(cli, keys.dep_ctl(tls.fleet, "edge-1"), payload=b"drain") == []
        assert _ok_replies(cli, keys.dep_probe(tls.fleet, "edge-1")) == []
        assert _ok_replies(cli, keys.svc_infer(tls.fleet, tls.cfg.service, "robot-1")) == []
    assert tls.ctl_calls == []


def test_the_cli_follows_a_robots_results_and_another_robot_cannot_forge_them(
    tls: TlsFleet,
) -> None:
    """`elasticfog results` (the CLI's certificate) receives robot-1's results on out/robot-1;
    robot-2 may not publish there."""
    got: list[bytes] = []
    own = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(sample.payload.to_bytes())
        if got[-1] == b"robot-1's":
            own.set()

    with open_session(tls.cfg, identity="cli", mode="client", listen=[]) as cli:
        cli.declare_subscriber(keys.results_out(tls.fleet, "robot-1"), on_sample)
        _barrier_token(tls, tls.router)

        def publish() -> bool:
            tls.robot2.put(keys.results_out(tls.fleet, "robot-1"), b"forged")
            tls.robot1.put(keys.results_out(tls.fleet, "robot-1"), b"robot-1's")
            return own.wait(0.5)

        _wait(publish, "robot-1's result at the CLI")
    assert b"forged" not in got


# -- who cannot connect at all ---------------------------------------------------------------------
def _raw_client(tls: TlsFleet, ca: Path, cert: Path | None, key: Path | None) -> zenoh.Config:
    """A client config straight to the router, without the preflight (what an attacker runs)."""
    conf = zenoh_config(mode="client", connect=[tls.endpoint], connect_timeout_s=2.0)
    conf.insert_json5("transport/link/tls/root_ca_certificate", f'"{ca}"')
    if cert is not None and key is not None:
        for side in ("connect", "listen"):
            conf.insert_json5(f"transport/link/tls/{side}_certificate", f'"{cert}"')
            conf.insert_json5(f"transport/link/tls/{side}_private_key", f'"{key}"')
    return conf


def test_a_client_without_a_certificate_cannot_connect(tls: TlsFleet) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(_raw_client(tls, tls.certs / "ca.crt", None, None)).close()


def test_a_host_with_a_certificate_from_another_ca_cannot_connect(
    tls: TlsFleet, tmp_path: Path
) -> None:
    other = tmp_path / "other"
    init_fleet_certs(other, ["robot-1"])
    with pytest.raises(zenoh.ZError):
        zenoh.open(_raw_client(tls, other / "ca.crt", other / "robot-1.crt", other / "robot-1.key"))
    # The preflight names why, within seconds: our CA does not know the registry's certificate.
    started = time.monotonic()
    with pytest.raises(CertError) as exc:
        probe_endpoint(tls.endpoint, TlsConfig(ca=str(other / "ca.crt"), cert=None, key=None))
    assert time.monotonic() - started < FAILURE_NAMED_WITHIN_S
    assert str(exc.value).startswith(tls.endpoint)
    assert "not signed by the fleet CA (unknown CA)" in str(exc.value)
    # Our CA is right but our certificate comes from elsewhere: the registry refuses it.
    foreign = TlsConfig(
        ca=str(tls.certs / "ca.crt"),
        cert=str(other / "robot-1.crt"),
        key=str(other / "robot-1.key"),
    )
    with pytest.raises(CertError, match="the peer refused this host's certificate"):
        probe_endpoint(tls.endpoint, foreign)


def test_a_daemon_with_a_foreign_certificate_fails_at_start(tls: TlsFleet, tmp_path: Path) -> None:
    """robot-1's files replaced by another CA's: one line naming the file, exit code 2."""
    other = tmp_path / "other"
    init_fleet_certs(other, ["robot-1"])
    cfg = tls.cfg.model_copy(deep=True)
    cfg.machines["robot-1"].tls = TlsConfig(
        cert=str(other / "robot-1.crt"), key=str(other / "robot-1.key")
    )
    started = time.monotonic()
    with pytest.raises(CertError) as exc:
        open_session(cfg, machine="robot-1")
    assert time.monotonic() - started < FAILURE_NAMED_WITHIN_S
    assert str(exc.value).startswith(str(other / "robot-1.crt"))
    assert "not signed by the fleet CA" in str(exc.value) and exc.value.exit_code == 2


@pytest.fixture
def rogue_registry(tls: TlsFleet, tmp_path: Path) -> Callable[..., str]:
    """`rogue_registry(**issue_kwargs)`: a router (no preflight) whose `registry` certificate is
    issued by the fleet CA with `issue_kwargs`; returns its endpoint."""
    opened: list[zenoh.Session] = []

    def start(**issue_kwargs: Any) -> str:
        directory = tmp_path / f"rogue{len(opened)}"
        shutil.copytree(tls.certs, directory)
        issue(directory, "registry", force=True, **issue_kwargs)
        endpoint = f"tls/127.0.0.1:{find_free_port()}"
        conf = zenoh_config(router=True, listen=[endpoint])
        for k, v in {
            "root_ca_certificate": directory / "ca.crt",
            "listen_certificate": directory / "registry.crt",
            "listen_private_key": directory / "registry.key",
        }.items():
            conf.insert_json5(f"transport/link/tls/{k}", f'"{v}"')
        opened.append(zenoh.open(conf))
        return endpoint

    try:
        yield start
    finally:
        for s in opened:
            s.close()


def _robot1_tls(tls: TlsFleet) -> TlsConfig:
    return tls.cfg.tls_for("robot-1")


def test_wrong_san_on_the_registry_is_named(tls: TlsFleet, rogue_registry: Any) -> None:
    endpoint = rogue_registry(sans=SanSpec(ips=(), dns=("registry.example.org",)))
    with pytest.raises(CertError) as exc:
        probe_endpoint(endpoint, _robot1_tls(tls))
    assert str(exc.value).startswith(endpoint) and "(wrong SAN)" in str(exc.value)


def test_expired_registry_certificate_is_named(tls: TlsFleet, rogue_registry: Any) -> None:
    import datetime as dt

    now = dt.datetime.now(dt.timezone.utc)
    endpoint = rogue_registry(
        not_before=now - dt.timedelta(days=3), not_after=now - dt.timedelta(days=1)
    )
    with pytest.raises(CertError) as exc:
        probe_endpoint(endpoint, _robot1_tls(tls))
    assert str(exc.value).startswith(endpoint) and "has expired" in str(exc.value)


def test_a_registry_not_there_yet_is_no_error(tls: TlsFleet) -> None:
    """Daemons start before the registry: nobody listening is not a certificate problem."""
    probe_endpoint(f"tls/127.0.0.1:{find_free_port()}", _robot1_tls(tls))


def test_a_plain_tcp_listener_is_named(tls: TlsFleet, free_port: int) -> None:
    with (
        open_session(router=True, listen=[f"tcp/127.0.0.1:{free_port}"]),
        pytest.raises(CertError, match="is it a tls/ endpoint"),
    ):
        probe_endpoint(f"tls/127.0.0.1:{free_port}", _robot1_tls(tls))


def test_the_registry_refuses_to_start_without_its_endpoints_san(
    tls: TlsFleet, tmp_path: Path
) -> None:
    directory = tmp_path / "certs"
    shutil.copytree(tls.certs, directory)
    issue(directory, "registry", force=True, sans=SanSpec(ips=("10.9.9.9",), dns=()))
    cfg = tls.cfg.model_copy(deep=True)
    cfg.registry.tls = TlsConfig(
        cert=str(directory / "registry.crt"), key=str(directory / "registry.key")
    )
    with pytest.raises(CertError) as exc:
        open_session(cfg, router=True)
    assert str(exc.value).startswith(str(directory / "registry.crt"))
    assert "no SAN for 127.0.0.1" in str(exc.value)
