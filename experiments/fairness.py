"""Per-robot fairness on one deployment (`elasticfog bench scale --fairness`).

One robot, the victim, sends at the bench's frame rate all along; a neighbour beside it on the
same deployment is polite (the same rate) or a hog (as fast as it can, several frames in
flight), in alternating phases, polite then hog, several rounds. The issue's bar: the hog raises
the victim's p95 latency by at most 20%. The comparison is the median over rounds of each kind's
per-phase p95 (a drifting load on the host moves single phases, not the median of several
alternated ones); the p95 of all of a kind's frames pooled is given beside it.

What a phase records besides the victim's latency, to tell the deployment's decisions from the
host's: the victim's p95 wait for a worker (`queue_s`, what the per-robot queues decide), its
p95 run (`compute_s`), the rest of its latency (Zenoh both ways, the client, the daemon's
receiving and decoding), and the CPU each process of the bench used and what everyone else on
the host did (`cpu_share`), on the deployment's CPUs too when it is pinned to them
(`--pin-cloud`: the cloud daemon on CPUs of its own, the load generators and the registry on the
others; `deploy.cpu_pinning`).
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

from common.config import FleetConfig
from experiments.load_generator import FrameOutcome, FrameRecord, LoadGenerator, summarize

from . import scale_defaults as defaults
from .cpu_share import CpuMeter
from .neighbour import NeighbourProcess
from .options import bench_workdir
from .report import fmt, md_table
from .scale import LOAD_KIND, ROUTED_TIMEOUT_S, ScaleOptions, running_fleet, settings_of
from .stats import percentile

KINDS = ("polite", "hog")
BAR_RATIO = 1.2
"""The issue's bar: the victim's p95 beside a hog at most 1.2x its p95 beside a polite one."""


def transport_p95_s(records: Sequence[FrameRecord]) -> float | None:
    """p95 of what the served frames' latency holds beyond the deployment's wait and run."""
    served = [r for r in records if r.outcome is FrameOutcome.SERVED]
    return percentile([r.latency_s - r.queue_s - r.compute_s for r in served], 95)


def measure_fairness(
    cfg: FleetConfig,
    victim: str,
    neighbour: str,
    *,
    fps: float,
    rounds: int = defaults.FAIRNESS_ROUNDS,
    phase_s: float = defaults.FAIRNESS_PHASE_S,
    hog_in_flight: int = defaults.FAIRNESS_HOG_IN_FLIGHT,
    cut: int = 0,
    codec: str = "raw",
    arrivals: str = "periodic",
    daemons: Mapping[str, int] | None = None,
    cloud_cpus: Collection[int] | None = None,
    log: Callable[[str], None] = lambda message: None,
) -> dict[str, Any]:
    """The victim's latency beside a polite neighbour and beside a hog, on one deployment.

    The victim sends at `fps` all along, from this process; the neighbour runs in a process of
    its own (`neighbour`). Phases alternate, `rounds` times: the neighbour sends at `fps` too
    (polite), then as fast as it can with `hog_in_flight` frames in flight (hog). `daemons`
    (name -> pid; "cloud" is the deployment) have their CPU read per phase beside this process
    ("generator") and the neighbour's; `cloud_cpus` are the CPUs the cloud is pinned to."""
    if cfg.source_path is None:
        raise ValueError("the fleet must come from a file (the neighbour process loads it)")
    daemons = dict(daemons or {})
    pause = threading.Event()  # timed measurement windows, not waits for readiness
    phases: list[tuple[str, float, float, dict[str, Any], dict[str, float]]] = []
    with (
        LoadGenerator(
            cfg, [victim], fps=fps, cut=cut, codec=codec, arrivals=arrivals
        ) as victim_gen,
        NeighbourProcess(
            str(cfg.source_path), neighbour, cut=cut, codec=codec, arrivals=arrivals
        ) as other,
    ):
        meter = CpuMeter(
            {**daemons, "generator": os.getpid(), "neighbour": other.pid},
            cloud="cloud" if "cloud" in daemons else None,
            cloud_cpus=cloud_cpus,
        )
        victim_gen.wait_served(ROUTED_TIMEOUT_S)
        for round_ in range(rounds):
            for kind in KINDS:
                hog = kind == "hog"
                other.start_phase(None if hog else fps, hog_in_flight if hog else 1, round_)
                t0, cpu0 = time.monotonic(), meter.read()
                pause.wait(phase_s)
                t1, cpu1 = time.monotonic(), meter.read()
                phases.append((kind, t0, t1, other.stop_phase(), meter.usage(cpu0, cpu1)))
    rows = []
    for kind, t0, t1, theirs, cpu in phases:
        records = victim_gen.records(t0, t1)
        mine = summarize(records, t1 - t0)
        rows.append(
            {
                "phase": kind,
                "victim_p50_latency_s": mine["p50_latency_s"],
                "victim_p95_latency_s": mine["p95_latency_s"],
                "victim_p95_queue_s": mine["p95_queue_s"],
                "victim_p95_compute_s": mine["p95_compute_s"],
                "victim_p95_transport_s": transport_p95_s(records),
                "victim_busy_rate": mine["busy_rate"],
                "victim_frames": mine["frames"],
                "neighbour_sent_fps": theirs["sent_fps"],
                "neighbour_served_fps": theirs["served_fps"],
                "neighbour_busy_rate": theirs["busy_rate"],
                **cpu,
            }
        )
        log(
            f"fairness {kind}: victim p95 {fmt(mine['p95_latency_s'], 4)} s (queue "
            f"{fmt(mine['p95_queue_s'], 4)}, compute {fmt(mine['p95_compute_s'], 4)}), neighbour "
            f"{theirs['served_fps']:.0f} frames/s served, busy {100 * theirs['busy_rate']:.0f}%; "
            f"cores: {', '.join(f'{k[:-6]} {v:.2f}' for k, v in cpu.items())}"
        )
    medians = {kind: phase_medians([r for r in rows if r["phase"] == kind]) for kind in KINDS}
    pooled = {
        kind: percentile(
            [
                rec.latency_s
                for k, t0, t1, _, _ in phases
                if k == kind
                for rec in victim_gen.records(t0, t1)
                if rec.outcome is FrameOutcome.SERVED
            ],
            95,
        )
        for kind in KINDS
    }
    polite, hogged = (
        medians["polite"]["victim_p95_latency_s"],
        medians["hog"]["victim_p95_latency_s"],
    )
    return {
        "phases": rows,
        "medians": medians,
        "polite_p95_s": polite,
        "hog_p95_s": hogged,
        "ratio": _ratio(hogged, polite),
        "polite_pooled_p95_s": pooled["polite"],
        "hog_pooled_p95_s": pooled["hog"],
        "pooled_ratio": _ratio(pooled["hog"], pooled["polite"]),
        "hog_busy_rate": medians["hog"]["neighbour_busy_rate"],
        "hog_served_fps": medians["hog"]["neighbour_served_fps"],
        "victim_busy_rate": max(r["victim_busy_rate"] for r in rows),
        "victim_frames_per_phase": min(r["victim_frames"] for r in rows),
    }


def phase_medians(rows: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """The median over phases of every numeric figure (None where no phase has one)."""
    keys = dict.fromkeys(k for r in rows for k in r if k != "phase")
    out: dict[str, float | None] = {}
    for key in keys:
        # NaN (a process gone before the phase's end) is no figure; neither is a missing one.
        values = [v for r in rows if isinstance(v := r.get(key), int | float) and v == v]
        out[key] = statistics.median(values) if values else None
    return out


def _ratio(hogged: float | None, polite: float | None) -> float | None:
    return hogged / polite if polite and hogged is not None else None


def run_fairness(options: ScaleOptions) -> dict[str, Any]:
    """The victim beside a polite neighbour and a hog on one deployment, with the per-robot
    in-flight limit (`options.max_in_flight_per_robot`) and heavy robots at low priority (the
    defaults), with the limit alone, and with neither (every slot): `variants`."""
    options.check()
    unlimited = options.workers * max(options.batch_sizes) + options.queue
    results = []
    with bench_workdir(options.workdir, "elasticfog-fairness-", options.log) as workdir:
        for batching in options.batching:
            for limit, low in variants(options.max_in_flight_per_robot, unlimited):
                limited = dataclasses.replace(
                    options, robots=(2,), max_in_flight_per_robot=limit, heavy_low_priority=low
                )
                label = f"fairness-{'on' if batching else 'off'}-limit{limit}-low{int(low)}"
                with running_fleet(limited, workdir, 1, batching, label) as fleet:
                    figures = measure_fairness(
                        fleet.cfg,
                        "robot-1",
                        "robot-2",
                        fps=options.fps,
                        cut=options.cut,
                        codec=options.codec,
                        arrivals=options.arrivals,
                        daemons={"cloud": fleet.clouds[0].pid, "registry": fleet.registry.pid},
                        cloud_cpus=None if fleet.cpus is None else fleet.cpus.cloud,
                        log=options.log,
                    )
                    figures["cloud_threads_off_cpus"] = fleet.threads_off_cpus()
                results.append(
                    {
                        "batching": "on" if batching else "off",
                        "max_in_flight_per_robot": limit,
                        "heavy_robots_low_priority": low,
                        **figures,
                    }
                )
    return {"load": LOAD_KIND, "settings": settings_of(options), "fairness": results}


def variants(limit: int, unlimited: int) -> list[tuple[int, bool]]:
    """(per-robot limit, heavy robots at low priority) per fleet: what a deployment does by
    default, then without the low priority, then without the limit either."""
    return [(limit, True), (limit, False), (unlimited, False)]


def fairness_markdown(result: dict[str, Any]) -> str:
    """The comparison per setting, then where the victim's time and the host's CPUs went."""
    settings = result["settings"]
    header = [
        "batching",
        "per-robot limit",
        "heavy robot at low priority",
        "victim p95, polite neighbour (s)",
        "victim p95, hog (s)",
        "ratio",
        "pooled ratio",
        "hog served frames/s",
        "hog busy",
        "victim busy",
    ]
    rows = [
        [
            r["batching"],
            r["max_in_flight_per_robot"],
            "yes" if r.get("heavy_robots_low_priority") else "no",
            fmt(r["polite_p95_s"], 4),
            fmt(r["hog_p95_s"], 4),
            fmt(r["ratio"], 2),
            fmt(r["pooled_ratio"], 2),
            fmt(r["hog_served_fps"], 0),
            f"{100 * (r['hog_busy_rate'] or 0):.0f}%",
            f"{100 * r['victim_busy_rate']:.0f}%",
        ]
        for r in result["fairness"]
    ]
    split_header = [
        "per-robot limit",
        "low priority",
        "phase",
        "wait p95 ms",
        "run p95 ms",
        "rest p95 ms",
        "neighbour sent/s",
        "cloud cores (Zenoh threads)",
        "generators cores",
        "others cores",
        "others on cloud CPUs",
        "steal",
    ]
    split_rows = []
    for r in result["fairness"]:
        for kind in KINDS:
            m = r["medians"][kind]
            split_rows.append(
                [
                    r["max_in_flight_per_robot"],
                    "yes" if r.get("heavy_robots_low_priority") else "no",
                    kind,
                    _ms(m["victim_p95_queue_s"]),
                    _ms(m["victim_p95_compute_s"]),
                    _ms(m["victim_p95_transport_s"]),
                    fmt(m["neighbour_sent_fps"], 0),
                    f"{fmt(m.get('cloud_cores'), 2)} ({fmt(m.get('cloud_zenoh_cores'), 2)})",
                    fmt(_sum(m.get("generator_cores"), m.get("neighbour_cores")), 2),
                    fmt(m.get("others_cores"), 2),
                    fmt(m.get("others_on_cloud_cpus_cores"), 2),
                    fmt(m.get("steal_cores"), 2),
                ]
            )
    pinning = settings.get("pin_cloud")
    where = (
        f"the cloud daemon pinned to CPU(s) {_cpus(pinning['cloud'])}, the registry and the load "
        f"generators to CPU(s) {_cpus(pinning['rest'])}"
        if pinning
        else "nothing pinned"
    )
    frames = min((r["victim_frames_per_phase"] for r in result["fairness"]), default=0)
    return (
        f"Load: {result['load']}; {settings['model']} at "
        f"{'x'.join(map(str, settings['input_shape']))}; the victim and the polite neighbour "
        f"send {settings['fps_per_robot']:g} fps ({settings.get('arrivals', 'periodic')}), "
        "the hog as fast as it can with "
        f"{defaults.FAIRNESS_HOG_IN_FLIGHT} frames in flight; medians of "
        f"{defaults.FAIRNESS_ROUNDS} alternating phases of {defaults.FAIRNESS_PHASE_S:g} s "
        f"(at least {frames} victim frames each); {settings['workers']} workers; {where}; "
        f"bar: ratio <= {BAR_RATIO:g}.\n\n"
        + md_table(header, rows)
        + "\n\nMedians over phases (the victim's wait for a worker, run, and the rest of its "
        "latency; cores used):\n\n" + md_table(split_header, split_rows) + "\n"
    )


def _ms(seconds: float | None) -> str:
    return "n/a" if seconds is None else f"{1000 * seconds:.1f}"


def _sum(*values: float | None) -> float | None:
    present = [v for v in values if v is not None]
    return sum(present) if present else None


def _cpus(cpus: Sequence[int]) -> str:
    return ",".join(map(str, cpus))
