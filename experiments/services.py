"""Several services on one robot: joint against independent decisions (`elasticfog bench services`).

One robot uses three services at once (`robotd.services`: one capture feeds them all, each has
its own policy, route and frame loop, and they share the robot's uplink and CPU): a classifier
(`zoo:mobilenet_v2` at 160x120, priority 2, deadline 0.15 s), a dense model
(`experiments.dense_model`: class scores for every pixel of a 320x240 image, priority 1,
deadline 0.3 s) and a handler (`perception.apriltag:detect` on 640x480, FogROS2-LS's workload,
priority 0, deadline 0.25 s; where the daemons cannot import it, a small OpenCV edge detector
the bench writes beside the fleet file). The networks' policy is `elastic`; the handler's is
`cloud:jpeg90` unless `--handler-policy` says otherwise (`HANDLER_POLICY`). One deployment,
`edge-1`, serves all three, at `fps` each. The robot's host is held at `robot_cpu` of a core
(0.5 by default) and its uplink is capped with `tc`: `UNCONTENDED_MBIT` first, then, while the
robot streams, `CONTENDED_MBIT`, where the handler's image alone (about 40 KB) takes 0.16 s to
cross and the three services' crossings together need most of the link.

After a robot run that is not measured (the deployment's and the host's first runs would
otherwise fall on the first measured run, always a joint one), each round runs the robot twice:
with `--decisions joint` (a service gives way, running on the robot, where the link share the
services ranking above it leave cannot carry its frame within its deadline,
`robotd.shared_budget`) and with `--decisions independent` (the same policies, each blind to
the others, as separate processes would be), in that order round after round, so that a drift
of the shared host falls on both. A run: the robot starts with the whole machine (start-up is
not measured), its host gets its quota, `warmup_frames` frames of every service are left out
(the services start streaming as each is ready, seconds apart: the warm-up ends with the last
one's), the uncontended phase lasts `phase_s`, then the cap drops; the first `settle_s` after
the change are left out (the policies learn the new link and the queue of the old rate drains),
the contended phase lasts `phase_s`, and the robot is stopped with SIGINT (its `--frames` is
only a bound). `services_rows` turns the records into rows.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from common.config import FleetConfig, fleet_from_dict
from common.daemon import FORCED_EXIT_CODE
from common.errors import UserError
from deploy.procs import DaemonError
from deploy.readiness import wait_until

from .dense_model import write_dense_model
from .fleet import ROBOT_HOST, ROBOT_ID, FleetSpec, endpoint, fleet_dict
from .options import BenchOptions, open_fleet
from .report import save_plot, use_agg
from .runner import NetnsDaemon, TestbedFleet
from .services_rows import (
    CONTENDED,
    INDEPENDENT,
    MODES,
    PHASES,
    UNCONTENDED,
    Goal,
    RunWindows,
    ServiceInfo,
    ServiceRow,
    SumRow,
    build_rows,
    goal,
    sum_rows,
)
from .services_rows import markdown as rows_markdown

HOSTS = ("registry", "robot", "edge-1", "bench")
CLOUD = "edge-1"
UNCONTENDED_MBIT = 20.0
CONTENDED_MBIT = 2.0
FPS = 5.0
"""Every service's frame rate (one capture feeds them all)."""
FULL_ROUNDS, QUICK_ROUNDS = 3, 1
FULL_PHASE_S, QUICK_PHASE_S = 20.0, 5.0
FULL_SETTLE_S, QUICK_SETTLE_S = 3.0, 2.0
FULL_WARMUP, QUICK_WARMUP = 8, 4
ROUTE_WAIT_S = 240.0
"""Bound of the wait for the registry to route every service to the deployment."""
WARMUP_WAIT_S = 300.0
"""Bound of the wait for every service's warm-up frames (start-up and calibration included)."""
CAP_MARGIN_S = 30.0
"""Seconds of frames beyond the start-up bound and the phases in the robot's --frames bound."""
WARM_UP_RUN_S = 5.0
"""How long the unmeasured first run streams past its warm-up frames."""
LEASE_MS = 10_000
"""The fleet's Zenoh lease: when the robot's three services started at once on the 2-core host,
a 3 s lease between the registry and `edge-1` lapsed in 4 of 16 runs, and the registry then left
the robot on itself for 2 to 4 minutes. Nothing here measures failure detection."""
HOLD_POLL_S = 0.2
"""How often a phase's wait looks at the robot (it must not exit meanwhile)."""

CLASSIFIER = "classify"
DENSE = "dense"
HANDLER = "tags"
APRILTAG_HANDLER = "perception.apriltag:detect"
APRILTAG_PARAMS = {"size_m": 0.16}
OWN_HANDLER_MODULE = "bench_edges"
OWN_HANDLER = f"{OWN_HANDLER_MODULE}:detect"
OWN_HANDLER_SOURCE = '''"""The handler `bench services` writes beside its fleet file when the
daemons cannot import perception.apriltag: OpenCV edges and their blobs (boxes, centres)."""

import cv2
import numpy as np

MIN_AREA_PX = 20


def detect(inputs, **params):
    grey = cv2.cvtColor(inputs["image"][0], cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(grey, (5, 5), 0), 60, 140)
    _, _, stats, centres = cv2.connectedComponentsWithStats(edges)
    keep = stats[1:, cv2.CC_STAT_AREA] >= MIN_AREA_PX
    return {
        "boxes": stats[1:, :4][keep].astype(np.int32),
        "centres": centres[1:][keep].astype(np.float32),
    }
'''

CLASSIFIER_MODEL = "zoo:mobilenet_v2"
CLASSIFIER_SHAPE = (3, 120, 160)
DENSE_SHAPE = (3, 240, 320)
HANDLER_SHAPE = (3, 480, 640)
# (priority, deadline_s) per service: the classifier ranks first and has the tightest deadline,
# the handler ranks last. At 2 Mbit/s the handler's 640x480 image at JPEG quality 90 (about 40 KB)
# takes 0.16 s to cross alone, within its deadline; beside the others' crossings, not always.
RANKS: dict[str, tuple[int, float]] = {
    CLASSIFIER: (2, 0.15),
    DENSE: (1, 0.3),
    HANDLER: (0, 0.25),
}
MODEL_POLICY = "elastic"
"""The networks' policy (learning where to cut them, frame by frame)."""
HANDLER_POLICY = "cloud:jpeg90"
"""The handler's default policy: always the deployment, the image at JPEG quality 90 (as
FogROS2-LS serves AprilTag detection from the cloud; a tag's corners, and so its pose, need the
image's detail). `--handler-policy elastic` lets it learn like the networks."""


@dataclass(frozen=True)
class ServicesSettings:
    """The runs' settings; the fields, in order, are the keys of its JSON object."""

    robot_cpu: float
    fps: float
    uplinks_mbit: dict[str, float]
    rounds: int
    warmup_frames: int
    phase_s: float
    settle_s: float
    frames_cap: int
    """The robot's --frames: a bound (each run is stopped once its phases are over)."""
    handler_policy: str = HANDLER_POLICY
    services: list[ServiceInfo] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["services"] = [s.to_json() for s in self.services]
        return out


@dataclass(frozen=True)
class ServicesResult:
    """Settings, one row per (mode, phase, service), the sums per (mode, phase), the goal and
    each run's windows."""

    settings: ServicesSettings
    results: list[ServiceRow]
    sums: list[SumRow]
    goal: Goal
    runs: list[RunWindows]

    def public(self) -> dict[str, Any]:
        """The `--json`: {"settings", "results": [rows], "sums": [rows], "goal", "runs"}."""
        return {
            "settings": self.settings.to_json(),
            "results": [r.to_json() for r in self.results],
            "sums": [s.to_json() for s in self.sums],
            "goal": self.goal.to_json(),
            "runs": [r.to_json() for r in self.runs],
        }


def plan(
    options: BenchOptions,
    *,
    rounds: int | None = None,
    fps: float = FPS,
    uncontended_mbit: float = UNCONTENDED_MBIT,
    contended_mbit: float = CONTENDED_MBIT,
    phase_s: float | None = None,
    handler_policy: str = HANDLER_POLICY,
) -> ServicesSettings:
    """The settings of a run from the options (--quick: shorter phases, one round); the
    services are filled in by `run` (the handler depends on what the daemons import)."""
    for what, value in (("--fps", fps), ("--uncontended-mbit", uncontended_mbit)):
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"{what} {value:g}: must be a positive number")
    if not (math.isfinite(contended_mbit) and 0 < contended_mbit < uncontended_mbit):
        raise UserError(
            f"--contended-mbit {contended_mbit:g}: must be positive and below "
            f"--uncontended-mbit ({uncontended_mbit:g})"
        )
    if rounds is not None and rounds < 1:
        raise UserError(f"--rounds {rounds}: expected at least 1")
    if phase_s is not None and not (math.isfinite(phase_s) and phase_s >= 2):
        raise UserError(f"--phase-s {phase_s:g}: expected at least 2 (seconds)")
    from robotd.policies import check_policy

    try:
        check_policy(handler_policy, real_time=True)
    except UserError as exc:
        raise UserError(f"--handler-policy: {exc}") from None
    quick = options.quick
    phase = phase_s if phase_s is not None else (QUICK_PHASE_S if quick else FULL_PHASE_S)
    settle = QUICK_SETTLE_S if quick else FULL_SETTLE_S
    warmup = QUICK_WARMUP if quick else FULL_WARMUP
    # A bound only: the start-up of the slowest service, the warm-up, both phases, a margin.
    frames_cap = math.ceil(fps * (WARMUP_WAIT_S + 2 * phase + settle + CAP_MARGIN_S))
    return ServicesSettings(
        robot_cpu=options.robot_cpu,
        fps=fps,
        uplinks_mbit={UNCONTENDED: uncontended_mbit, CONTENDED: contended_mbit},
        rounds=rounds or (QUICK_ROUNDS if quick else FULL_ROUNDS),
        warmup_frames=warmup,
        phase_s=phase,
        settle_s=settle,
        frames_cap=frames_cap,
        handler_policy=handler_policy,
    )


# -- the fleet -------------------------------------------------------------------------------------
def handler_spec(run_dir: Path) -> tuple[str, dict[str, Any]]:
    """The handler the daemons will run: perception.apriltag:detect when their interpreter
    imports it (asked from a folder of no package, as the `elasticfog` script sees it), else the
    bench's own edge detector, written beside the fleet file (searched first for handlers)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    module = APRILTAG_HANDLER.partition(":")[0]
    found = subprocess.run(
        [sys.executable, "-c", f"import {module}"],
        cwd=run_dir,
        capture_output=True,
        timeout=60,
        check=False,
    )
    if found.returncode == 0:
        return APRILTAG_HANDLER, dict(APRILTAG_PARAMS)
    (run_dir / f"{OWN_HANDLER_MODULE}.py").write_text(OWN_HANDLER_SOURCE, encoding="utf-8")
    return OWN_HANDLER, {}


def services(
    run_dir: Path, handler_policy: str = HANDLER_POLICY
) -> tuple[list[ServiceInfo], dict[str, dict[str, Any]]]:
    """The three services (what they are, and fleet.yaml's `services:` mapping); writes the
    dense model and, if needed, the handler into `run_dir`."""
    dense = write_dense_model(run_dir, DENSE_SHAPE)
    handler, params = handler_spec(run_dir)
    handler_keys: dict[str, Any] = {"handler": handler, **({"params": params} if params else {})}
    kinds: dict[str, tuple[str, str, tuple[int, int, int], dict[str, Any]]] = {
        CLASSIFIER: ("classifier", CLASSIFIER_MODEL, CLASSIFIER_SHAPE, {"model": CLASSIFIER_MODEL}),
        DENSE: ("dense", dense.name, DENSE_SHAPE, {"model": str(dense)}),
        HANDLER: ("handler", handler, HANDLER_SHAPE, handler_keys),
    }
    infos, mapping = [], {}
    for name, (kind, runs, shape, what) in kinds.items():
        priority, deadline_s = RANKS[name]
        policy = handler_policy if kind == "handler" else MODEL_POLICY
        infos.append(ServiceInfo(name, runs, kind, shape, priority, deadline_s, policy))
        mapping[name] = {
            **what,
            "priority": priority,
            "deadline_s": deadline_s,
            "policy": {"kind": policy},
        }
        if kind != "dense":  # the file's own dimensions are fixed
            mapping[name]["input_shape"] = list(shape)
    return infos, mapping


def fleet_spec(tf: TestbedFleet, settings: ServicesSettings) -> tuple[FleetSpec, list[ServiceInfo]]:
    """The fleet of the bench (its folder made, the dense model and any handler written in it):
    `edge-1` serving the three services to `robot-1` at `fps`."""
    name = tf.next_fleet_name("svc-")
    infos, mapping = services(tf.workdir / name, settings.handler_policy)
    spec = FleetSpec(
        fleet=name,
        clouds=(CLOUD,),
        services=mapping,
        deadline_s=max(i.deadline_s for i in infos),
        fps=settings.fps,
        lease_ms=LEASE_MS,
        # Each service's frame loop holds a session of its own, and each would listen on the
        # robot's one fixed port: port 0 lets each take a free one (gossip tells the peers).
        changes={
            "machines": {
                ROBOT_ID: {"listen": [endpoint(tf.testbed.address(ROBOT_HOST), 0, tls=tf.tls)]}
            },
        },
    )
    return spec, infos


def prepare(tf: TestbedFleet, spec: FleetSpec, run_dir: Path) -> None:
    """Split every service's model into the cache before any daemon starts (they load it)."""
    from common.fleet_model import fleet_partition

    data = fleet_dict(spec, tf.testbed.addresses(), run_dir / "prepare.sqlite")
    cfg: FleetConfig = fleet_from_dict(data, source=run_dir / f"{spec.fleet}.yaml")
    for name in cfg.services:
        fleet_partition(cfg.for_service(name))


# -- the runs ----------------------------------------------------------------------------------
def run(
    options: BenchOptions,
    settings: ServicesSettings,
) -> ServicesResult:
    options.check()
    runs: list[RunWindows] = []
    with open_fleet(options, hosts=HOSTS) as tf:
        spec, infos = fleet_spec(tf, settings)
        settings = ServicesSettings(**{**_fields(settings), "services": infos})
        options.log(
            "services: " + ", ".join(f"{i.name} ({i.runs}, priority {i.priority})" for i in infos)
        )
        prepare(tf, spec, tf.workdir / spec.fleet)
        tf.launch(spec, prepare=False)
        options.log("a warm-up run (not measured)")
        warm_up(tf, settings, infos)
        for turn in range(settings.rounds):
            for mode in MODES:
                options.log(f"round {turn + 1} of {settings.rounds}: --decisions {mode}")
                runs.append(run_once(tf, settings, infos, mode, turn))
    rows = build_rows(runs, infos, settings.uplinks_mbit)
    sums = sum_rows(rows)
    return ServicesResult(settings, rows, sums, goal(sums), runs)


def _fields(settings: ServicesSettings) -> dict[str, Any]:
    return {f: getattr(settings, f) for f in settings.__dataclass_fields__}


def warm_up(tf: TestbedFleet, settings: ServicesSettings, infos: list[ServiceInfo]) -> None:
    """A robot run that is not measured, before the first round: the deployment's first
    frames of each service (its sessions' first runs) and the host's caches would otherwise
    fall on the first measured run, always a joint one."""
    robot = _start(tf, settings, infos, INDEPENDENT, "warm-up")
    _hold(robot, WARM_UP_RUN_S)
    _stop(robot, tf)


def run_once(
    tf: TestbedFleet,
    settings: ServicesSettings,
    infos: list[ServiceInfo],
    mode: str,
    turn: int,
) -> RunWindows:
    """One robot run in `mode`: warm-up, the uncontended phase, the change, the contended
    phase; then the robot is stopped (SIGINT: the frames in flight are finished and reported)."""
    robot = _start(tf, settings, infos, mode, f"{mode}-{turn + 1}")
    start = time.time()
    _hold(robot, settings.phase_s)
    tf.shape_robot(settings.uplinks_mbit[CONTENDED])
    change = time.time()
    _hold(robot, settings.settle_s + settings.phase_s)
    stop = time.time()
    _stop(robot, tf)
    records = tf.follower.records()
    windows = {UNCONTENDED: (start, change), CONTENDED: (change + settings.settle_s, stop)}
    run = RunWindows(mode, turn + 1, records, windows)
    phases = ", ".join(f"{p} {len(_of(run, infos, p))} frames" for p in PHASES)
    tf.log(f"{mode}: {phases}")
    return run


def _start(
    tf: TestbedFleet, settings: ServicesSettings, infos: list[ServiceInfo], mode: str, tag: str
) -> NetnsDaemon:
    """The robot in `mode` on the uncontended uplink, under its quota, past every service's
    warm-up frames. The services start streaming as each is ready, seconds apart: the warm-up
    waits for the last. The frame in flight when the quota came ran partly unthrottled: the
    warm-up counts after it."""
    tf.shape_robot(settings.uplinks_mbit[UNCONTENDED])
    robot = tf.start_robot(
        None,
        frames=settings.frames_cap,
        cpu_fraction=settings.robot_cpu,
        extra=["--decisions", mode],
        tag=tag,
    )
    _wait_routes(tf, infos, robot)
    last = _last_frames(tf.follower.records(), infos)
    for info in infos:
        tf.follower.wait_for(
            _frame_of(info.name, last[info.name] + 2 + settings.warmup_frames),
            timeout_s=WARMUP_WAIT_S,
            what=f"{settings.warmup_frames} warm-up frames of service {info.name}",
            procs=[robot],
        )
    return robot


def _wait_routes(tf: TestbedFleet, infos: list[ServiceInfo], robot: NetnsDaemon) -> None:
    """Until the registry routes every service of the robot to the deployment: on a loaded
    host its lease to `edge-1` may lapse, and the robot is then routed to itself until the
    registry places it again (minutes), which would measure a robot without a deployment."""
    assert tf.observer is not None
    observer = tf.observer
    wanted = {i.name for i in infos}

    def routed() -> bool:
        rows = observer.view("routes", timeout_s=2.0)
        served = {
            r.get("service")
            for r in rows
            if r.get("robot") == ROBOT_ID and r.get("deployment") == CLOUD
        }
        return wanted <= served

    wait_until(
        routed,
        timeout_s=ROUTE_WAIT_S,
        what=f"the registry to route every service of {ROBOT_ID} to {CLOUD}",
        procs=[robot],
        interval_s=0.5,
    )


def _stop(robot: NetnsDaemon, tf: TestbedFleet) -> None:
    """SIGINT (the robot finishes its frames in flight, starts no more), its quota lifted. A
    robot that stopped its frame loops but not its Zenoh sessions within its limit leaves
    with FORCED_EXIT_CODE: its records are written, the run counts."""
    stopped = robot.stop()
    tf.cpu_robot(None)
    if stopped.returncode == FORCED_EXIT_CODE and not stopped.killed:
        tf.log(f"{robot.name}: its sessions did not close in time (exit {FORCED_EXIT_CODE})")
        return
    if stopped.killed or stopped.returncode != 0:
        raise DaemonError(
            f"{robot.name} did not stop cleanly (exit {stopped.returncode}, "
            f"{'killed' if stopped.killed else 'not killed'}); log: {robot.log_path}"
        )


def _of(run: RunWindows, infos: list[ServiceInfo], phase: str) -> list[Any]:
    return [r for i in infos for r in run.in_phase(i.name, phase)]


def _frame_of(service: str, frame: int) -> Callable[[dict[str, Any]], bool]:
    """Whether a record is of `service`, frame `frame` or later."""
    return lambda r: r.get("service") == service and int(r.get("frame", -1)) >= frame


def _last_frames(records: list[dict[str, Any]], infos: list[ServiceInfo]) -> dict[str, int]:
    last = {i.name: -1 for i in infos}
    for r in records:
        name = r.get("service")
        if name in last:
            last[name] = max(last[name], int(r.get("frame", -1)))
    return last


def _hold(robot: NetnsDaemon, seconds: float) -> None:
    """A phase's length: `seconds` while the robot streams (it must not exit meanwhile)."""
    until = time.monotonic() + seconds
    while (left := until - time.monotonic()) > 0:
        if robot.poll() is not None:
            robot.check_alive()
            raise DaemonError(
                f"{robot.name} ran its {robot.args[robot.args.index('--frames') + 1]} frames "
                f"before the phases ended; log: {robot.log_path}"
            )
        time.sleep(min(HOLD_POLL_S, left))


# -- output --------------------------------------------------------------------------------------
def markdown(result: ServicesResult) -> str:
    s = result.settings
    head = (
        f"robot {s.robot_cpu:g} core, {s.fps:g} fps per service, policies "
        + ", ".join(f"{i.name} {i.policy}" for i in s.services)
        + ", "
        f"{s.rounds} round(s) of joint and independent runs alternated, phases of "
        f"{s.phase_s:g} s ({s.settle_s:g} s left out after the change)\n\n"
    )
    return head + rows_markdown(result.results, result.sums, result.goal, s.uplinks_mbit)


def plot(result: ServicesResult, out_dir: Path) -> list[Path]:
    """p95 latency per service, joint beside independent, one panel per phase."""
    use_agg()
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PHASES), figsize=(10, 4), sharey=True)
    names = [i.name for i in result.settings.services]
    width = 0.38
    for ax, phase in zip(axes, PHASES, strict=True):
        for k, mode in enumerate(MODES):
            values = [
                next(
                    (
                        r.p95_latency_s or 0.0
                        for r in result.results
                        if r.mode == mode and r.phase == phase and r.service == n
                    ),
                    0.0,
                )
                for n in names
            ]
            xs = [i + (k - 0.5) * width for i in range(len(names))]
            ax.bar(xs, values, width, label=mode)
        ax.set_xticks(range(len(names)), names)
        ax.set_title(f"{phase} uplink ({result.settings.uplinks_mbit[phase]:g} Mbit/s)")
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].set_ylabel("p95 latency (s)")
    axes[0].legend()
    fig.suptitle(f"three services on a robot of {result.settings.robot_cpu:g} core")
    return [save_plot(fig, out_dir / "services.png")]
