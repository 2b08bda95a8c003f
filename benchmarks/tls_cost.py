"""What mutual TLS costs: the Zenoh round trip of a 1 MiB request over `tls/` against plain `tcp/`,
in one run, between two processes on loopback.

The request is a real `InferRequest` from `common.wire` carrying one float32 tensor of the asked
size, answered with a tiny reply (what a robot does per offloaded frame). The server is a separate
process (never fork after zenoh.open) holding two peer sessions: one listening on tcp/, one on
tls/ with mutual TLS and certificates made by `common.certs` for this run. The client opens one
session to each and alternates them round by round, so both see the same machine state. Shared
memory is off (it would bypass both links). The server prints one line when its sessions are up;
the client waits for that line and then for the first reply on each link.

    python benchmarks/tls_cost.py [--size-mib 1] [--rounds 200] [--json]

Target (issue 13): TLS median <= 1.5x plain TCP. Results are in docs/security.md.
"""

from __future__ import annotations

import argparse
import json
import select
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.zenoh_vs_tcp import free_port, make_payload

KEY_TCP = "ef/bench/tls-cost/tcp"
KEY_TLS = "ef/bench/tls-cost/tls"
READY_TIMEOUT_S = 30.0
QUERY_TIMEOUT_S = 5.0
WARMUP_ROUNDS = 20
TARGET_RATIO = 1.5


def session_config(certs: Path | None, host: str, **kwargs: Any) -> Any:
    """The runtime's session settings (common.session), plus mutual TLS as `host` if `certs`."""
    from common.session import zenoh_config

    conf = zenoh_config(mode="peer", shared_memory=False, **kwargs)
    if certs is not None:
        files = {
            "root_ca_certificate": certs / "ca.crt",
            "listen_certificate": certs / f"{host}.crt",
            "listen_private_key": certs / f"{host}.key",
            "connect_certificate": certs / f"{host}.crt",
            "connect_private_key": certs / f"{host}.key",
        }
        for name, path in files.items():
            conf.insert_json5(f"transport/link/tls/{name}", json.dumps(str(path)))
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
    return conf


# -- server ----------------------------------------------------------------------------------------
def serve(tcp_port: int, tls_port: int, certs: Path) -> None:
    """Both echo sessions until stdin closes (the client's way of saying it is done)."""
    import zenoh

    def on_query(query: zenoh.Query) -> None:
        # Touch the payload like a deployment would before it decodes it.
        _ = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(query.key_expr, b"ok")

    plain_conf = session_config(None, "server", listen=[f"tcp/127.0.0.1:{tcp_port}"], connect=[])
    tls_conf = session_config(certs, "server", listen=[f"tls/127.0.0.1:{tls_port}"], connect=[])
    with zenoh.open(plain_conf) as plain, zenoh.open(tls_conf) as tls:
        q1 = plain.declare_queryable(KEY_TCP, on_query, complete=True)
        q2 = tls.declare_queryable(KEY_TLS, on_query, complete=True)
        print("ready", flush=True)
        sys.stdin.read()
        q1.undeclare()
        q2.undeclare()


# -- client ----------------------------------------------------------------------------------------
def stats_ms(samples: list[float]) -> dict[str, float]:
    ordered = sorted(samples)
    return {
        "median_ms": statistics.median(ordered) * 1e3,
        "mean_ms": statistics.fmean(ordered) * 1e3,
        "p95_ms": ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))] * 1e3,
        "min_ms": ordered[0] * 1e3,
    }


def run(size_mib: float, rounds: int) -> dict[str, Any]:
    import zenoh

    from common.certs import init_fleet_certs

    payload = make_payload(size_mib)
    with tempfile.TemporaryDirectory(prefix="tls-cost-") as tmp:
        certs = Path(tmp)
        init_fleet_certs(certs, ["server", "client"], days=1)
        tcp_port, tls_port = free_port(), free_port()
        server = subprocess.Popen(
            [sys.executable, __file__, "--serve", str(tcp_port), str(tls_port), str(certs)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        assert server.stdin is not None and server.stdout is not None
        try:
            ready, _, _ = select.select([server.stdout], [], [], READY_TIMEOUT_S)
            if not ready or server.stdout.readline().strip() != b"ready":
                raise RuntimeError("server did not start")
            plain_conf = session_config(
                None, "client", listen=[], connect=[f"tcp/127.0.0.1:{tcp_port}"]
            )
            tls_conf = session_config(
                certs, "client", listen=[], connect=[f"tls/127.0.0.1:{tls_port}"]
            )
            with zenoh.open(plain_conf) as plain, zenoh.open(tls_conf) as tls:

                def rtt(session: zenoh.Session, key: str) -> float:
                    t0 = time.perf_counter()
                    replies = list(
                        session.get(
                            key,
                            payload=payload,
                            timeout=QUERY_TIMEOUT_S,
                            congestion_control=zenoh.CongestionControl.BLOCK,
                        )
                    )
                    dt = time.perf_counter() - t0
                    if not replies or replies[0].ok is None:
                        raise RuntimeError(f"no reply on {key}")
                    return dt

                for session, key in ((plain, KEY_TCP), (tls, KEY_TLS)):
                    deadline = time.monotonic() + READY_TIMEOUT_S
                    while True:  # the queryable reaches us once the peers have connected
                        try:
                            rtt(session, key)
                            break
                        except RuntimeError:
                            if time.monotonic() > deadline:
                                raise
                for _ in range(WARMUP_ROUNDS):
                    rtt(plain, KEY_TCP)
                    rtt(tls, KEY_TLS)
                tcp_samples: list[float] = []
                tls_samples: list[float] = []
                for _ in range(rounds):  # interleaved: both links see the same moments
                    tcp_samples.append(rtt(plain, KEY_TCP))
                    tls_samples.append(rtt(tls, KEY_TLS))
        finally:
            server.stdin.close()
            try:
                server.wait(timeout=10)
            except subprocess.TimeoutExpired:
                server.kill()
    results: dict[str, Any] = {
        "payload_bytes": len(payload),
        "rounds": rounds,
        "tcp": stats_ms(tcp_samples),
        "tls": stats_ms(tls_samples),
    }
    results["ratio_median"] = results["tls"]["median_ms"] / results["tcp"]["median_ms"]
    results["target_ratio"] = TARGET_RATIO
    results["meets_target"] = results["ratio_median"] <= TARGET_RATIO
    return results


def table(results: dict[str, Any]) -> str:
    rows = [
        "| link | median ms | mean ms | p95 ms | min ms |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for name in ("tcp", "tls"):
        s = results[name]
        rows.append(
            f"| {name}/ | {s['median_ms']:.2f} | {s['mean_ms']:.2f} | {s['p95_ms']:.2f} | "
            f"{s['min_ms']:.2f} |"
        )
    verdict = "meets" if results["meets_target"] else "MISSES"
    rows.append("")
    rows.append(
        f"{results['payload_bytes']} B request, {results['rounds']} rounds each, interleaved; "
        f"TLS/TCP median ratio {results['ratio_median']:.2f} ({verdict} the "
        f"<= {results['target_ratio']:g}x target)"
    )
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mib", type=float, default=1.0)
    parser.add_argument("--rounds", type=int, default=200)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--serve", nargs=3, metavar=("TCP_PORT", "TLS_PORT", "CERTS"))
    args = parser.parse_args()
    if args.serve:
        serve(int(args.serve[0]), int(args.serve[1]), Path(args.serve[2]))
        return
    results = run(args.size_mib, args.rounds)
    print(json.dumps(results, indent=2) if args.json else table(results))


if __name__ == "__main__":
    main()
