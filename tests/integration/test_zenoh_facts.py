"""The Zenoh behaviours the design rests on (DESIGN.md, "Zenoh facts"), checked with real sessions
on loopback, configured by `common.session`:

- anycast: two `complete=True` queryables on one key, a BEST_MATCHING get: exactly one answers;
  without `complete=True` both do (why the service key must be declared complete);
- peers that only know the router still link to each other directly (gossip), and keep talking
  when the router is gone (the registry is not on the data path);
- a liveliness token is seen when declared and gone when undeclared or its session closes;
- a 1 MiB tensor makes the round trip intact through the wire codec.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.wire import decode
from common.wire.cloud_to_robot import INFER_REPLIES, InferReply
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor, decode_tensors

FLEET = "facts"
QUERY_TIMEOUT_S = 5.0
QUERIES = 10


def _serve(
    session: zenoh.Session, key: str, name: str, calls: dict[str, int], *, complete: bool
) -> Any:
    lock = threading.Lock()

    def on_query(query: zenoh.Query) -> None:
        with lock:
            calls[name] += 1
        query.reply(key, name.encode())

    return session.declare_queryable(key, on_query, complete=complete)


def _answers(session: zenoh.Session, key: str) -> list[str]:
    # No consolidation: replies on the same key would otherwise be merged into one, hiding a
    # second answer.
    replies = session.get(
        key,
        target=zenoh.QueryTarget.BEST_MATCHING,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=QUERY_TIMEOUT_S,
    )
    return [reply.ok.payload.to_string() for reply in replies if reply.ok is not None]


def _two_servers(
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    key: str,
    *,
    complete: bool,
) -> tuple[zenoh.Session, dict[str, int], list[Any]]:
    """Two peers serving `key`, and a third that has seen both (their tokens are declared after
    their queryables, on the same session, so seeing the token means the queryable is known)."""
    calls = {"edge-1": 0, "edge-2": 0}
    held: list[Any] = []
    for name in calls:
        server = open_peer()
        held.append(_serve(server, key, name, calls, complete=complete))
        held.append(server.liveliness().declare_token(keys.alive_deployment(FLEET, name)))
    client = open_peer()
    for name in calls:
        wait_for_token(client, keys.alive_deployment(FLEET, name))
    return client, calls, held


def test_anycast_complete_queryables_exactly_one_answers(
    open_peer: Callable[..., zenoh.Session], wait_for_token: Callable[..., None]
) -> None:
    key = keys.svc_infer(FLEET, "vision", "robot-1")
    client, calls, _held = _two_servers(open_peer, wait_for_token, key, complete=True)
    for _ in range(QUERIES):
        assert len(_answers(client, key)) == 1
    assert sum(calls.values()) == QUERIES


def test_without_complete_every_queryable_runs(
    open_peer: Callable[..., zenoh.Session], wait_for_token: Callable[..., None]
) -> None:
    key = keys.svc_infer(FLEET, "vision", "robot-2")
    client, calls, _held = _two_servers(open_peer, wait_for_token, key, complete=False)
    assert sorted(_answers(client, key)) == ["edge-1", "edge-2"]
    assert calls == {"edge-1": 1, "edge-2": 1}


def test_peers_link_directly_and_survive_the_router(
    zenoh_router: Any,
    open_peer: Callable[..., zenoh.Session],
    wait_for_peer: Callable[..., None],
    wait_for_token: Callable[..., None],
) -> None:
    server, client = open_peer(), open_peer()
    wait_for_peer(client, server.zid())  # both only know the router: gossip linked them
    key = keys.dep_probe(FLEET, "edge-1")
    calls = {"edge-1": 0}
    _queryable = _serve(server, key, "edge-1", calls, complete=True)
    _token = server.liveliness().declare_token(keys.alive_deployment(FLEET, "edge-1"))
    wait_for_token(client, keys.alive_deployment(FLEET, "edge-1"))
    assert _answers(client, key) == ["edge-1"]
    zenoh_router.session.close()  # the registry's router dies; robot <-> deployment goes on
    assert _answers(client, key) == ["edge-1"]
    assert calls["edge-1"] == 2


def test_liveliness_token_seen_on_declare_and_gone_on_undeclare(
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    wait_for_token_gone: Callable[..., None],
) -> None:
    watcher, holder = open_peer(), open_peer()
    key = keys.alive_deployment(FLEET, "edge-1")
    events: list[tuple[str, zenoh.SampleKind]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            events.append((str(sample.key_expr), sample.kind))

    subscriber = watcher.liveliness().declare_subscriber(keys.alive_deployments(FLEET), on_sample)
    token = holder.liveliness().declare_token(key)
    wait_for_token(watcher, key)
    seed = [str(r.ok.key_expr) for r in watcher.liveliness().get(keys.alive_all(FLEET)) if r.ok]
    assert seed == [key]

    token.undeclare()
    wait_for_token_gone(watcher, key)
    assert not [r for r in watcher.liveliness().get(keys.alive_all(FLEET)) if r.ok]
    subscriber.undeclare()
    with lock:
        assert events[0] == (key, zenoh.SampleKind.PUT)
        assert events[-1] == (key, zenoh.SampleKind.DELETE)


def test_liveliness_token_gone_when_its_session_closes(
    open_peer: Callable[..., zenoh.Session],
    wait_for_token: Callable[..., None],
    wait_for_token_gone: Callable[..., None],
) -> None:
    watcher, holder = open_peer(), open_peer()
    key = keys.alive_robot(FLEET, "robot-1")
    _token = holder.liveliness().declare_token(key)  # undeclared if garbage-collected
    wait_for_token(watcher, key)
    holder.close()
    wait_for_token_gone(watcher, key, timeout_s=2.0)  # well under the lease: the socket closed


def test_one_mebibyte_tensor_round_trip(
    open_peer: Callable[..., zenoh.Session], wait_for_token: Callable[..., None]
) -> None:
    server, client = open_peer(), open_peer()
    key = keys.svc_infer(FLEET, "vision", "robot-1")

    def echo(query: zenoh.Query) -> None:
        assert query.payload is not None
        request = InferRequest.from_wire(query.payload.to_bytes())
        reply = InferReply(
            frame=request.frame,
            deployment="edge-1",
            epoch=request.epoch,
            outputs=decode_tensors(request.tensors, max_bytes=tensor.nbytes),
            queue_s=0.0,
            compute_s=0.0,
        )
        query.reply(key, reply.to_wire())

    _queryable = server.declare_queryable(key, echo, complete=True)
    _token = server.liveliness().declare_token(keys.alive_deployment(FLEET, "edge-1"))
    wait_for_token(client, keys.alive_deployment(FLEET, "edge-1"))

    tensor = np.random.default_rng(0).standard_normal(256 * 1024).astype(np.float32)
    assert tensor.nbytes == 1024 * 1024
    request = InferRequest(
        robot="robot-1",
        frame=1,
        model_digest="ab" * 32,
        cut=0,
        tensors={"input": EncodedTensor.raw(tensor)},
        deadline_s=QUERY_TIMEOUT_S,
        sent_at=0.0,
    )
    replies = list(
        client.get(
            key,
            payload=request.to_wire(),
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=QUERY_TIMEOUT_S,
        )
    )
    assert len(replies) == 1 and replies[0].ok is not None
    reply = decode(replies[0].ok.payload.to_bytes(), expect=INFER_REPLIES)
    assert isinstance(reply, InferReply)
    assert np.array_equal(reply.outputs["input"], tensor)
