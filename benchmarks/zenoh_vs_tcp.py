"""Round trip of a 1 MiB tensor: a Zenoh query (what a robot does per offloaded frame) against a
raw TCP socket carrying the same bytes, in one run, between two processes on loopback.

The request is a real `InferRequest` from `common.wire` carrying one float32 tensor of the asked
size; the TCP side sends exactly those bytes (length-prefixed) and both servers answer a tiny
reply, so the difference is what Zenoh adds over a bare socket: its framing, routing, query
bookkeeping and Python bindings. The server is a separate process started with subprocess (never
fork after zenoh.open), listening on free loopback ports; it prints one line when both listeners
are up, which is what the client waits for. Zenoh sessions are peers with multicast scouting off
(the runtime's settings); shared memory is measured off (the network path) and on.

    python benchmarks/zenoh_vs_tcp.py [--size-mib 1] [--rounds 200] [--json]
"""

from __future__ import annotations

import argparse
import json
import select
import socket
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

KEY = "ef/bench/echo"
LEN_PREFIX = struct.Struct("!Q")
ACK = b"ok"
READY_TIMEOUT_S = 30.0
QUERY_TIMEOUT_S = 5.0
WARMUP_ROUNDS = 20


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def recv_exact(conn: socket.socket, n: int, buf: bytearray) -> memoryview:
    view = memoryview(buf)[:n]
    got = 0
    while got < n:
        k = conn.recv_into(view[got:], n - got)
        if k == 0:
            raise ConnectionError("peer closed")
        got += k
    return view


# -- server ----------------------------------------------------------------------------------------
def serve(zenoh_port: int, tcp_port: int, shm: bool) -> None:
    """Both echo servers until stdin closes (the client's way of saying it is done)."""
    import threading

    import zenoh

    from common.session import open_session

    def on_query(query: zenoh.Query) -> None:
        # Touch the payload like a deployment would before it decodes it.
        _ = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(query.key_expr, ACK)

    def tcp_server(listener: socket.socket) -> None:
        conn, _ = listener.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        buf = bytearray(64 << 20)
        with conn:
            while True:
                try:
                    (n,) = LEN_PREFIX.unpack(recv_exact(conn, LEN_PREFIX.size, buf))
                    _ = bytes(recv_exact(conn, n, buf))  # the same one copy as to_bytes()
                except ConnectionError:
                    return
                conn.sendall(ACK)

    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", tcp_port))
    listener.listen(1)
    threading.Thread(target=tcp_server, args=(listener,), daemon=True).start()
    with open_session(
        mode="peer", listen=[f"tcp/127.0.0.1:{zenoh_port}"], connect=[], shared_memory=shm
    ) as session:
        queryable = session.declare_queryable(KEY, on_query, complete=True)
        print("ready", flush=True)
        sys.stdin.read()  # until the client closes our stdin
        queryable.undeclare()
    listener.close()


# -- client ----------------------------------------------------------------------------------------
def make_payload(size_mib: float) -> bytes:
    from common.wire.robot_to_cloud import InferRequest
    from common.wire.tensor_codecs import EncodedTensor

    n = int(size_mib * (1 << 20)) // 4
    tensor = np.random.default_rng(0).standard_normal(n).astype(np.float32)
    return InferRequest(
        robot="robot-1",
        frame=0,
        model_digest="0" * 64,
        cut=0,
        tensors={"input": EncodedTensor.raw(tensor)},
        deadline_s=1.0,
        sent_at=time.time(),
    ).to_wire()


def stats_ms(samples: list[float]) -> dict[str, float]:
    ordered = sorted(samples)
    return {
        "median_ms": statistics.median(ordered) * 1e3,
        "mean_ms": statistics.fmean(ordered) * 1e3,
        "p95_ms": ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))] * 1e3,
        "min_ms": ordered[0] * 1e3,
    }


def run(size_mib: float, rounds: int, shm: bool) -> dict[str, Any]:
    import zenoh

    from common.session import open_session

    payload = make_payload(size_mib)
    zport, tport = free_port(), free_port()
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve", str(zport), str(tport), "--shm", str(int(shm))],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    assert server.stdin is not None and server.stdout is not None
    try:
        ready, _, _ = select.select([server.stdout], [], [], READY_TIMEOUT_S)
        if not ready or server.stdout.readline().strip() != b"ready":
            raise RuntimeError("server did not start")
        results: dict[str, Any] = {"payload_bytes": len(payload), "rounds": rounds, "shm": shm}

        with open_session(
            mode="peer", listen=[], connect=[f"tcp/127.0.0.1:{zport}"], shared_memory=shm
        ) as session:

            def zenoh_rtt() -> float:
                t0 = time.perf_counter()
                replies = list(
                    session.get(
                        KEY,
                        payload=payload,
                        timeout=QUERY_TIMEOUT_S,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                )
                dt = time.perf_counter() - t0
                if not replies or replies[0].ok is None:
                    raise RuntimeError("no zenoh reply")
                return dt

            deadline = time.monotonic() + READY_TIMEOUT_S
            while True:  # the server's queryable reaches us once the peers have connected
                try:
                    zenoh_rtt()
                    break
                except RuntimeError:
                    if time.monotonic() > deadline:
                        raise
            for _ in range(WARMUP_ROUNDS):
                zenoh_rtt()
            results["zenoh"] = stats_ms([zenoh_rtt() for _ in range(rounds)])

        with socket.create_connection(("127.0.0.1", tport), timeout=QUERY_TIMEOUT_S) as conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            header = LEN_PREFIX.pack(len(payload))
            ack = bytearray(len(ACK))

            def tcp_rtt() -> float:
                t0 = time.perf_counter()
                conn.sendall(header)
                conn.sendall(payload)
                recv_exact(conn, len(ACK), ack)
                return time.perf_counter() - t0

            for _ in range(WARMUP_ROUNDS):
                tcp_rtt()
            results["tcp"] = stats_ms([tcp_rtt() for _ in range(rounds)])
        results["ratio_median"] = results["zenoh"]["median_ms"] / results["tcp"]["median_ms"]
        return results
    finally:
        server.stdin.close()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mib", type=float, default=1.0)
    parser.add_argument("--rounds", type=int, default=200)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--serve", nargs=2, type=int, metavar=("ZENOH_PORT", "TCP_PORT"))
    parser.add_argument("--shm", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve[0], args.serve[1], bool(args.shm))
        return
    rows = [run(args.size_mib, args.rounds, shm) for shm in (False, True)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"payload {rows[0]['payload_bytes']} bytes, {args.rounds} round trips each, loopback\n")
    print("| path | shared memory | median ms | mean ms | p95 ms | min ms |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for row in rows:
        for path in ("zenoh", "tcp"):
            s = row[path]
            label = "zenoh get (peer to peer)" if path == "zenoh" else "raw TCP socket"
            shm = ("on" if row["shm"] else "off") if path == "zenoh" else "-"
            print(
                f"| {label} | {shm} | {s['median_ms']:.3f} | {s['mean_ms']:.3f} | "
                f"{s['p95_ms']:.3f} | {s['min_ms']:.3f} |"
            )
    for row in rows:
        print(
            f"\nzenoh/tcp median ratio (shm {'on' if row['shm'] else 'off'}): "
            f"{row['ratio_median']:.1f}x"
        )


if __name__ == "__main__":
    main()
