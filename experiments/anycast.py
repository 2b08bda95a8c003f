"""FogROS2-LS Table I on the testbed: deadline misses when the serving deployment is slowed.

The robot offloads every frame (`--policy cloud`, as FogROS2-LS offloads perception) at a fixed
frame rate to the anycast service key, served at start by `edge-1`. After a warm-up, fault
injection on `edge-1` (its ctl key, at run time) makes its replies late: on 100% of requests
(an added delay far beyond the deadline) or on 50% of them (half the requests never answered).
For the robot both are the same thing, a reply that misses the frame's deadline, after which it
finishes the frame itself. With more deployments the registry can move the robot away from
`edge-1`; the miss rate is the share of frames after the injection whose latency exceeded the
deadline. The other deployments stand for places further away: `edge-2` is as near as `edge-1`,
`cloud-1` and `cloud-2` answer later (a fixed delay injected from the start) over a capped
downlink, so they are slower but still inside the deadline.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .fleet import ROBOT_HOST, FleetSpec
from .options import BenchOptions, open_fleet
from .report import fmt, md_table, save_plot, use_agg
from .runner import TestbedFleet
from .stats import between, by_frame, lost_frames

# The paper's columns: Edge 1 only; + Edge 2; + Cloud (W); + Cloud (E); + both clouds; and all.
DEPLOYMENT_SETS: tuple[tuple[str, ...], ...] = (
    ("edge-1",),
    ("edge-1", "edge-2"),
    ("edge-1", "cloud-1"),
    ("edge-1", "cloud-2"),
    ("edge-1", "cloud-1", "cloud-2"),
    ("edge-1", "edge-2", "cloud-1", "cloud-2"),
)
MODES = ("100%", "50%")
DEADLINE_S = 0.25
"""The task's deadline per frame (the robot's `deadline_s`): a reply later than this is a miss."""
SLOW_DELAY_MS = 1000.0
"""Injected on edge-1 for "100%": every reply comes 4 deadlines late."""
HALF_DROP = 0.5
"""Injected on edge-1 for "50%": half of the requests are never answered."""
FAR = {"cloud-1": (30.0, 100.0), "cloud-2": (60.0, 50.0)}
"""Deployment -> (delay added to every reply ms, downlink cap Mbit/s): further away."""
ROBOT_UPLINK_MBIT = 100.0
FPS = 10.0
LATENCY_BOUND = {"stat": "median", "seconds": 0.15, "window": 8, "hysteresis_s": 0.5}
FULL_FRAMES, QUICK_FRAMES = 100, 40
WARMUP_FRAMES = 40
"""4 s at 10 fps: the robot has probed every deployment twice before the fault."""
RUN_SLACK_S = 120.0


def run_one(
    tf: TestbedFleet, options: BenchOptions, deployments: Sequence[str], mode: str, frames: int
) -> dict[str, Any]:
    spec = FleetSpec(
        fleet=tf.next_fleet_name("ac-"),
        clouds=tuple(deployments),
        serving="edge-1",
        model=options.model,
        input_shape=options.input_shape,
        deadline_s=DEADLINE_S,
        latency_bound=LATENCY_BOUND,
        policy="cloud",
        lease_ms=1000,
        changes={
            "machines": {d: {"fault": {"delay_ms": FAR[d][0]}} for d in deployments if d in FAR}
        },
    )
    tf.reset_conditions()
    tf.shape_robot(ROBOT_UPLINK_MBIT)
    for d in deployments:
        if d in FAR:
            tf.tb.shape(d, None, FAR[d][1])
    tf.launch(spec)
    total = WARMUP_FRAMES + frames
    robot = tf.start_robot("cloud", frames=total, fps=FPS)
    tf.follower.wait_frame(tf.measure_from + WARMUP_FRAMES - 1, timeout_s=60.0, procs=[robot])
    assert tf.observer is not None
    if mode == "100%":
        tf.observer.fault("edge-1", delay_ms=SLOW_DELAY_MS)
    else:
        tf.observer.fault("edge-1", drop=HALF_DROP)
    fault_frame = tf.follower.last_frame() + 1
    options.log(f"{'+'.join(deployments)} ({mode}): edge-1 slowed at frame {fault_frame}")
    records = by_frame(tf.finish_robot(RUN_SLACK_S + total * (DEADLINE_S + 1.0)))
    window = between(records, fault_frame)
    misses = [r for r in window if float(r["latency_s"]) > DEADLINE_S or r.get("fallback")]
    served: dict[str, int] = {}
    for r in window:
        key = str(r.get("deployment")) if r.get("deployment") and not r.get("fallback") else "robot"
        served[key] = served.get(key, 0) + 1
    tf.stop_daemons()
    return {
        "deployments": list(deployments),
        "mode": mode,
        "frames": len(window),
        "misses": len(misses),
        "miss_rate": len(misses) / len(window) if window else None,
        "served_by": served,
        "lost": len(lost_frames(records, total)),
        "fault_frame": fault_frame,
    }


def run(
    options: BenchOptions,
    sets: Sequence[Sequence[str]] = DEPLOYMENT_SETS,
    modes: Sequence[str] = MODES,
) -> dict[str, Any]:
    options.check()
    frames = options.frames_or(FULL_FRAMES, QUICK_FRAMES)
    hosts = ("registry", ROBOT_HOST, "edge-1", "edge-2", "cloud-1", "cloud-2", "bench")
    results = []
    with open_fleet(options, hosts=hosts) as tf:
        for mode in modes:
            for deployments in sets:
                results.append(run_one(tf, options, deployments, mode, frames))
    return {
        "settings": {
            "model": options.model,
            "input_shape": list(options.input_shape),
            "deadline_s": DEADLINE_S,
            "fps": FPS,
            "frames_after_fault": frames,
            "slow_delay_ms": SLOW_DELAY_MS,
            "half_drop": HALF_DROP,
            "far": {k: {"delay_ms": v[0], "downlink_mbit": v[1]} for k, v in FAR.items()},
            "latency_bound": LATENCY_BOUND,
        },
        "results": results,
    }


def _label(deployments: Sequence[str]) -> str:
    return " + ".join(deployments)


def markdown(result: dict[str, Any]) -> str:
    sets = list(dict.fromkeys(tuple(r["deployments"]) for r in result["results"]))
    modes = list(dict.fromkeys(r["mode"] for r in result["results"]))
    header = ["edge-1 slowed on", *(_label(s) for s in sets)]
    rows = []
    for mode in modes:
        cells = []
        for s in sets:
            r = next(
                (
                    x
                    for x in result["results"]
                    if tuple(x["deployments"]) == s and x["mode"] == mode
                ),
                None,
            )
            if r is None or r["miss_rate"] is None:
                cells.append("n/a")
            else:
                cells.append(f"{100 * r['miss_rate']:.1f}% ({r['misses']}/{r['frames']})")
        rows.append([f"{mode} of requests", *cells])
    served = []
    for mode in modes:
        for r in (x for x in result["results"] if x["mode"] == mode):
            by = ", ".join(f"{k} {v}" for k, v in sorted(r["served_by"].items()))
            served.append([f"{mode}: {_label(r['deployments'])}", by, str(r["lost"])])
    return (
        md_table(header, rows)
        + "\n\n**who served the frames after the fault (lost frames)**\n\n"
        + md_table(["run", "served by", "lost"], served)
        + "\n"
    )


def plot(result: dict[str, Any], out_dir: Path) -> list[Path]:
    use_agg()
    import matplotlib.pyplot as plt

    sets = list(dict.fromkeys(tuple(r["deployments"]) for r in result["results"]))
    modes = list(dict.fromkeys(r["mode"] for r in result["results"]))
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / max(1, len(modes))
    for i, mode in enumerate(modes):
        values = []
        for s in sets:
            r = next(
                (
                    x
                    for x in result["results"]
                    if tuple(x["deployments"]) == s and x["mode"] == mode
                ),
                None,
            )
            values.append(0.0 if r is None or r["miss_rate"] is None else 100 * r["miss_rate"])
        xs = [j + i * width for j in range(len(sets))]
        ax.bar(xs, values, width=width, label=f"edge-1 slowed on {mode} of requests")
    ax.set_xticks([j + width * (len(modes) - 1) / 2 for j in range(len(sets))])
    ax.set_xticklabels(["\n+ ".join(s) for s in sets], fontsize=8)
    ax.set_ylabel(f"deadline misses (%), deadline {fmt(result['settings']['deadline_s'], 2)} s")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend()
    return [save_plot(fig, out_dir / "anycast.png")]
