"""`elasticfog bench pool`: the navigation assistant's round-robin scale-out on the testbed.

The paper replicates its 3D point-cloud workers and sends the frames to them in turn, so that a
stage slower than the camera keeps up: p >= ceil(t_p / T_f) workers for a processing time t_p and
a camera period T_f. Here the stage is the whole stereo pipeline in the cloud (zoo:stereo,
`stereo:world` frames, option 1: the robot sends the pair and gets d_coll back), each deployment
one onnxruntime thread and one worker on a host held at `cloud_cpu` of a core, so that one
deployment is slower than the camera and the pool is what scales.

For each pool size P a fresh fleet runs P cloud daemons (`CLOUD_HOSTS` in order, the first the
primary) with `dispatch: {mode: round_robin, pool_size: P}`, and the robot streams N frames at
`fps` with P frames in flight: one per member, so a member never queues a frame of this robot and
its t_p (`cloud_s`, queue plus compute) stays the compute time the sizing rule is about. Rows are
figured by `nav_pool_rows`; the cloud daemons' own counts come from their probe replies (the
frames each answered for the robot, `served`) before they stop, and from their exit summaries
(requests computed) after.

Unless `kill` is off, one more run with the largest pool and one standby deployment SIGKILLs a
member that is not the primary (the last one the route's pool lists) after a third of the frames,
and reads the route's pool from the registry's routes view until the standby replaces it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from common.errors import UserError
from deploy.procs import DaemonError
from deploy.readiness import wait_until

from .fleet import CLOUD_HOSTS, ROBOT_ID, FleetSpec
from .nav import CALIBRATION_FRAMES, DEFAULT_UPLINK_MBIT, MODEL, SOURCE
from .nav_pool_rows import (
    KillEvent,
    PoolRun,
    kill_summary,
    p_needed,
    parse_computed,
    pool_row,
    reference_t_p,
)
from .nav_rows import resolution_label
from .options import BenchOptions, open_fleet
from .report import fmt, md_table
from .runner import TestbedFleet

POLICY = "option:1"
"""The whole stereo pipeline in the cloud: the option with the largest t_p."""
DEFAULT_SIZES = (1, 2, 3)
DEFAULT_RESOLUTION = (320, 240)
DEFAULT_CLOUD_CPU = 0.5
"""Cores per cloud host: at 320x240 one deployment then takes several camera periods a frame."""
DEFAULT_FPS = 10.0
FULL_FRAMES, QUICK_FRAMES = 80, 30
FULL_WARMUP, QUICK_WARMUP = 5, 3
IN_FLIGHT_PER_MEMBER = 1
"""The robot's `--max-in-flight` is P times this: one frame at each member at a time."""
CLOUD_THREADS = 1
CLOUD_WORKERS = 1
DEADLINE_S = 10.0
"""Far above a frame's time under the cloud quota at 320x240 (about half a second): no frame is
cut off while the pool is whole, and the frames in flight at a killed member end on the robot
within it."""
POOL_WAIT_S = 30.0
"""How long the registry's route may take to list the whole pool, or the standby after a kill."""
ROUTE_POLL_S = 0.2
RUN_SLACK_S = 180.0
KILL_AT_FRACTION = 1 / 3
HOSTS = ("registry", "robot", *CLOUD_HOSTS, "bench")
MAX_FPS = 100.0


@dataclass(frozen=True)
class PoolSettings:
    """What `bench pool` runs beyond the shared bench options."""

    sizes: tuple[int, ...] = DEFAULT_SIZES
    resolution: tuple[int, int] = DEFAULT_RESOLUTION
    cloud_cpu: float = DEFAULT_CLOUD_CPU
    fps: float = DEFAULT_FPS
    uplink_mbit: float = DEFAULT_UPLINK_MBIT
    kill: bool = True

    def check(self) -> None:
        if not (math.isfinite(self.cloud_cpu) and 0.01 <= self.cloud_cpu <= 16):
            raise UserError(f"--cloud-cpu {self.cloud_cpu:g}: expected 0.01 to 16 (cores)")
        if not (math.isfinite(self.fps) and 0 < self.fps <= MAX_FPS):
            raise UserError(f"--fps {self.fps:g}: expected more than 0 and at most {MAX_FPS:g}")
        if not (math.isfinite(self.uplink_mbit) and self.uplink_mbit > 0):
            raise UserError(f"--uplink-mbit {self.uplink_mbit:g}: must be a positive number")
        if not self.sizes or min(self.sizes) < 1:
            raise UserError("--sizes: expected pool sizes from 1")
        hosts = len(CLOUD_HOSTS) - (1 if self.kill else 0)
        if max(self.sizes) > hosts:
            raise UserError(f"--sizes {max(self.sizes)}: at most {hosts} with these hosts")


def _fleet_spec(
    fleet: str, size: tuple[int, int], clouds: tuple[str, ...], pool_size: int
) -> FleetSpec:
    return FleetSpec(
        fleet=fleet,
        clouds=clouds,
        serving=clouds[0],
        model=MODEL,
        input_shape=(3, size[1], size[0]),
        deadline_s=DEADLINE_S,
        cloud_threads=CLOUD_THREADS,
        cloud_workers=CLOUD_WORKERS,
        changes={
            "machines": {ROBOT_ID: {"source": SOURCE}},
            "fidelity": {"calibration_frames": CALIBRATION_FRAMES},
            "dispatch": {"mode": "round_robin", "pool_size": pool_size},
        },
    )


def route_pool(tf: TestbedFleet) -> list[str]:
    """The robot's pool as the registry's routes view lists it now, its route's deployment first
    (no route: empty; an anycast route: its deployment alone)."""
    assert tf.observer is not None
    route = next(
        (r for r in tf.observer.view("routes", timeout_s=2.0) if r.get("robot") == ROBOT_ID), None
    )
    if route is None or not route.get("deployment"):
        return []
    return [str(d) for d in route.get("pool") or [route["deployment"]]]


def _wait_route(
    tf: TestbedFleet, done: Any, what: str, options: BenchOptions
) -> tuple[list[str], float | None]:
    """Poll the routes view until `done(pool)`; (the pool last seen, seconds it took or None).

    A route that does not get there is reported, not fatal: the run's telemetry still says who
    answered the frames."""
    started = time.monotonic()
    seen: list[list[str]] = [[]]

    def check() -> bool:
        seen[0] = route_pool(tf)
        return bool(done(seen[0]))

    try:
        wait_until(check, timeout_s=POOL_WAIT_S, what=what, interval_s=ROUTE_POLL_S)
    except DaemonError as exc:
        options.log(f"{exc}; the route lists {seen[0] or 'nothing'}")
        return seen[0], None
    return seen[0], time.monotonic() - started


def _cloud_counts(
    tf: TestbedFleet, clouds: tuple[str, ...], dead: set[str]
) -> dict[str, int | None]:
    """Frames each live cloud daemon says it answered for the robot (its probe reply)."""
    assert tf.observer is not None
    served: dict[str, int | None] = {}
    for cloud in clouds:
        if cloud in dead:
            served[cloud] = None
            continue
        try:
            reply = tf.observer.call("probe", deployment=cloud, timeout_s=2.0)["reply"]
        except DaemonError:
            served[cloud] = None
            continue
        served[cloud] = int(reply.get("served", {}).get(ROBOT_ID, 0))
    return served


def run_one(
    tf: TestbedFleet,
    options: BenchOptions,
    settings: PoolSettings,
    pool_size: int,
    frames: int,
    warmup: int,
    *,
    kill: bool = False,
) -> tuple[PoolRun, KillEvent | None]:
    """One fleet, one robot run against a pool of `pool_size` (with `kill`: a standby beside it
    and a member killed after a third of the frames)."""
    clouds = CLOUD_HOSTS[: pool_size + (1 if kill else 0)]
    tf.reset_conditions()
    tf.launch(_fleet_spec(tf.next_fleet_name("pool-"), settings.resolution, clouds, pool_size))
    tf.shape_robot(settings.uplink_mbit)
    for cloud in clouds:  # after start-up: loading and warming the model is not measured
        tf.tb.cpu(cloud, settings.cloud_cpu)
    in_flight = IN_FLIGHT_PER_MEMBER * pool_size
    robot = tf.start_robot(
        POLICY,
        frames=frames,
        fps=settings.fps,
        cpu_fraction=options.robot_cpu,
        extra=["--max-in-flight", str(in_flight)],
    )
    first = tf.measure_from
    tf.follower.wait_frame(first, timeout_s=RUN_SLACK_S, procs=[robot])
    pool, _ = _wait_route(
        tf, lambda p: len(p) >= pool_size, f"a pool of {pool_size} in the route", options
    )
    # Frames sent before the whole pool was in the route are not what is measured.
    measure_from = max(first + warmup, tf.follower.last_frame() + 1 + in_flight)
    event: KillEvent | None = None
    dead: set[str] = set()
    if kill:
        primary = pool[0] if pool else clouds[0]
        # A member that is not the primary, if the pool has one: the primary is also the
        # anycast route, whose loss the anycast experiments already measure.
        victim = pool[-1] if len(pool) > 1 else primary
        standby = tuple(c for c in clouds if c not in pool)
        kill_at = min(frames - 1, max(measure_from, int(frames * KILL_AT_FRACTION)))
        tf.follower.wait_frame(kill_at, timeout_s=RUN_SLACK_S, procs=[robot])
        tf.daemon(victim).kill()
        dead.add(victim)
        kill_frame = tf.follower.last_frame() + 1
        options.log(f"killed {victim} (SIGKILL) at frame {kill_frame}; pool was {pool}")
        after, repaired_s = _wait_route(
            tf,
            lambda p: victim not in p and any(s in p for s in standby),
            f"the route to drop {victim} and enlist a standby",
            options,
        )
        event = KillEvent(primary, victim, kill_frame, standby, pool, after, repaired_s)
    records = tf.finish_robot(RUN_SLACK_S + frames * (DEADLINE_S + 1))
    served = _cloud_counts(tf, clouds, dead)
    logs = {cloud: tf.daemon(cloud).log_path for cloud in clouds}
    tf.stop_daemons()  # a stopped cloud daemon logs what it computed
    computed = {
        cloud: parse_computed(path.read_text(errors="replace"), cloud)
        for cloud, path in logs.items()
    }
    run = PoolRun(
        pool_size=pool_size,
        max_in_flight=in_flight,
        frames=frames,
        measure_from=measure_from,
        records=records,
        pool=pool,
        served=served,
        computed=computed,
    )
    return run, event


def run(options: BenchOptions, settings: PoolSettings) -> dict[str, Any]:
    """The whole experiment: {"settings", "results" (a row per pool size), "kill" (or None)}."""
    options.check()
    settings.check()
    frames = options.frames_or(FULL_FRAMES, QUICK_FRAMES)
    warmup = min(QUICK_WARMUP if options.quick else FULL_WARMUP, max(0, frames - 3))
    label = resolution_label(settings.resolution)
    runs: list[PoolRun] = []
    kill: dict[str, Any] | None = None
    with open_fleet(options, hosts=HOSTS) as tf:
        for pool_size in settings.sizes:
            options.log(f"{label}, pool of {pool_size}: {frames} frames at {settings.fps:g} fps")
            runs.append(run_one(tf, options, settings, pool_size, frames, warmup)[0])
        if settings.kill:
            largest = max(settings.sizes)
            options.log(f"{label}, pool of {largest} and a standby: a member killed")
            kill_run, event = run_one(tf, options, settings, largest, frames, warmup, kill=True)
            assert event is not None
            kill = kill_summary(kill_run, event)
    t_p_s = reference_t_p(runs)
    needed = p_needed(t_p_s, settings.fps)
    return {
        "settings": {
            "model": MODEL,
            "source": SOURCE,
            "policy": POLICY,
            "resolution": label,
            "fps": settings.fps,
            "frame_period_s": 1.0 / settings.fps,
            "cloud_cpu": settings.cloud_cpu,
            "cloud_threads": CLOUD_THREADS,
            "cloud_workers": CLOUD_WORKERS,
            "robot_cpu": options.robot_cpu,
            "uplink_mbit": settings.uplink_mbit,
            "frames": frames,
            "warmup_frames": warmup,
            "in_flight_per_member": IN_FLIGHT_PER_MEMBER,
            "deadline_s": DEADLINE_S,
            "t_p_reference_s": t_p_s,
            "p_needed": needed,
        },
        "results": [pool_row(r, settings.resolution, needed) for r in runs],
        "kill": kill,
    }


def _counts(counts: dict[str, Any]) -> str:
    return ", ".join(f"{k} {fmt(v)}" for k, v in counts.items()) or "—"


def _names(names: list[str]) -> str:
    return ", ".join(names) or "empty"


def markdown(result: dict[str, Any]) -> str:
    """The pool table, the sizing rule from the measured t_p, and the kill run."""
    s = result["settings"]
    out = [
        f"zoo:stereo option 1 at {s['resolution']}, `{s['source']}` frames at {s['fps']:g} fps "
        f"(T_f = {s['frame_period_s']:.3f} s), each deployment 1 thread on {s['cloud_cpu']:g} "
        f"core, robot {s['robot_cpu']:g} core, uplink {s['uplink_mbit']:g} Mbit/s, "
        f"{s['frames']} frames per run ({s['warmup_frames']} left out), one frame in flight "
        "per pool member."
    ]
    rows = [
        [r["pool_size"], fmt(r["update_hz"], 2), *(fmt(r[k], 3) for k in
         ("t_o_s", "t_p_s", "t_c_s", "t_f_s")), _counts(r["answered_by"]),
         _counts(r["fallbacks"]), r["lost"], "yes" if r["each_frame_once"] else "NO"]
        for r in result["results"]
    ]  # fmt: skip
    header = ["P", "update (Hz)", "t_o (s)", "t_p (s)", "t_c (s)", "t_f (s)", "answered by",
              "fallbacks", "lost", "each frame once"]  # fmt: skip
    out.append("**Update frequency per pool size**\n\n" + md_table(header, rows))
    if s["p_needed"] is not None:
        out.append(
            f"p >= ceil(t_p / T_f) = ceil({s['t_p_reference_s']:.3f} / "
            f"{s['frame_period_s']:.3f}) = **{s['p_needed']}** deployments keep up with the "
            "camera (t_p from the smallest pool's run)."
        )
    kill = result.get("kill")
    if kill:
        out.append(_kill_markdown(kill))
    return "\n\n".join(out) + "\n"


def _kill_markdown(kill: dict[str, Any]) -> str:
    which = "the primary" if kill["killed_primary"] else "not the primary"
    repaired = kill["repaired_after_s"]
    joined = f"after {repaired:.1f} s" if repaired is not None else "not within the wait"
    header = ["", "before the kill", "after the kill"]
    rows = [
        ["answered by", _counts(kill["answered_before"]), _counts(kill["answered_after"])],
        ["update (Hz)", fmt(kill["update_hz_before"], 2), fmt(kill["update_hz_after"], 2)],
    ]
    return (
        f"**A member killed** (pool of {kill['pool_size']}, standby "
        f"{_names(kill['standby'])}): {kill['killed']} ({which}) SIGKILLed at frame "
        f"{kill['kill_frame']}; the route's pool {_names(kill['pool_before'])} before, "
        f"{_names(kill['pool_after'])} after (standby enlisted {joined}).\n\n"
        + md_table(header, rows)
        + f"\n\nlost {kill['lost']}, fallbacks {_counts(kill['fallbacks'])}, each frame once: "
        + ("yes" if kill["each_frame_once"] else "NO")
    )
