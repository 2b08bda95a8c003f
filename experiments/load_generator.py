"""Emulated robots: real inference requests over Zenoh to a fleet's deployments, for load tests.

What Triton's perf_analyzer is to a model server, this is to the cloud daemons: each emulated
robot declares its liveliness token (`alive/robot/<id>`, so the registry routes it as it routes
a real robot), sends one frame at a time to its anycast service key (`svc/<service>/<robot>/infer`)
with the fleet's deadline, and records how the frame ended: served (by which deployment, after
how long, with the deployment's own queue and compute times), `busy`, an error reply (its code),
a timeout (no reply within the deadline), or no route (nobody serves the robot yet). A robot
sends its next frame at its next tick of `fps`, or at once when a reply came after the tick (a
camera's frame loop drops the frames it had no time for); `fps=None` sends as soon as the reply
is in (closed loop: a robot "as fast as it can"). Ticks are periodic (a camera), or with
`arrivals="poisson"` exponentially spaced at the same mean rate, as perf_analyzer's
`--request-distribution poisson`: robots at exactly the same rate keep the phase they started
with, so whether two of them collide on a deployment is a lottery drawn once per start; Poisson
arrivals draw it again at every frame, as robots that are not synchronised see it.

Frames a deployment does not serve are the ones a real robot would finish itself; the generator
does not compute them, it counts them, and the robot waits `local_s` (the time it would spend
computing the frame) before its next one. A robot with `in_flight` > 1 keeps that many frames in
flight (a pipelined robot; with `fps=None`, one sending as fast as it can). Nothing else of a
robot runs here (no policy, no telemetry), so the registry never moves these robots for their
latency.

Payloads are real: the model's prefix for the chosen cut run once on a few photographs
(`common.photos`, through the robot's own input adapter), each tensor encoded with the chosen
codec, under the fleet's model digest. Every frame builds its message anew (frame number, send
time), around the same tensors.

All robots share one Zenoh peer session: the generator is one process with one set of Zenoh
threads, taking as little of the host's CPU from the daemons under test as it can; each robot
has a thread per frame in flight. Use it as a context manager (the session, the tokens and the
threads are released on exit).
"""

from __future__ import annotations

import contextlib
import enum
import itertools
import logging
import math
import random
import statistics
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from common import keys
from common.config import FleetConfig
from common.errors import UserError
from common.fleet_model import fleet_partition
from common.image_input import InputAdapter
from common.partition import sample_feeds
from common.partition.runtime import SplitModel
from common.photos import still_views
from common.session import open_session
from common.wire import ErrorReply, WireError, decode, encode_tensor_as, parse_codec
from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import EncodedTensor
from experiments.stats import percentile

log = logging.getLogger(__name__)

PAYLOAD_FRAMES = 4
"""Distinct frames whose tensors the robots send in turn (content varies as a camera's does)."""

LOCAL_S = 0.05
"""How long an emulated robot takes to finish a frame the cloud did not serve (about what a small
robot computer takes for the bench's models)."""

ARRIVALS = ("periodic", "poisson")
"""How a robot's frames are spaced: a camera's ticks, or exponential gaps of the same mean."""

JOIN_TIMEOUT_S = 5.0
"""How long stopping waits for a robot's thread (at most one deadline is in flight)."""


class FrameOutcome(enum.Enum):
    """How one frame ended, as the robot saw it."""

    SERVED = "served"
    BUSY = "busy"
    ERROR = "error"
    TIMEOUT = "timeout"
    NO_ROUTE = "no_route"


@dataclass(frozen=True)
class FrameRecord:
    """One frame of one emulated robot: sent at `sent_at` (monotonic seconds), answered after
    `latency_s` (for a timeout: the time waited)."""

    robot: str
    frame: int
    sent_at: float
    latency_s: float
    outcome: FrameOutcome
    deployment: str = ""
    queue_s: float = 0.0
    compute_s: float = 0.0
    detail: str = ""


def cut_payloads(
    cfg: FleetConfig, cut: int, codec: str, frames: int = PAYLOAD_FRAMES
) -> tuple[str, list[dict[str, EncodedTensor]]]:
    """The fleet model's digest and `frames` sets of cut `cut`'s tensors, encoded with `codec`
    (the robot's prefix run on photographs; random input for a model without one image input)."""
    model = SplitModel(fleet_partition(cfg), lazy=True)
    if not 0 <= cut < model.num_cuts:
        raise UserError(f"cut {cut}: this model has cuts 0..{model.num_cuts - 1}")
    try:
        parse_codec(codec)
    except WireError as exc:
        raise UserError(f"codec: {exc.reason}") from None
    specs = model.input_specs()
    feeds_list: list[dict[str, Any]]
    if len(specs) == 1:
        adapter = InputAdapter(specs[0])
        feeds_list = [{specs[0].name: adapter(view)} for view in still_views(frames)]
    else:
        feeds_list = [sample_feeds(specs, seed=i) for i in range(frames)]
    payloads = []
    with model:
        for feeds in feeds_list:
            tensors = model.run_prefix(cut, feeds)
            try:
                payloads.append({n: encode_tensor_as(a, codec) for n, a in tensors.items()})
            except WireError as exc:
                raise UserError(f"codec {codec} cannot carry cut {cut}: {exc.reason}") from None
    return model.digest, payloads


def frame_gap_s(period_s: float, poisson: random.Random | None) -> float:
    """Seconds from one tick of a robot's lane to the next: the period, or with a random source
    (Poisson arrivals) an exponential gap whose mean is the period."""
    return period_s if poisson is None else poisson.expovariate(1.0 / period_s)


class EmulatedRobot:
    """One robot's frame loop (see the module docstring): `in_flight` lanes, each on a thread of
    its own with one frame at a time (a pipelined robot keeps several frames in flight)."""

    def __init__(
        self,
        generator: LoadGenerator,
        robot: str,
        fps: float | None,
        *,
        in_flight: int = 1,
        phase_s: float = 0.0,
        poisson: random.Random | None = None,
    ) -> None:
        if in_flight < 1:
            raise ValueError(f"in_flight must be >= 1, got {in_flight}")
        self.robot = robot
        self.fps = fps
        self._gen = generator
        self._phase_s = phase_s
        self._poisson = poisson
        """With Poisson arrivals, the random source of this robot's gaps (None: periodic)."""
        self._key = keys.svc_infer(generator.cfg.fleet, generator.cfg.service_name, robot)
        self._records: list[FrameRecord] = []
        self._lock = threading.Lock()
        self._frames = itertools.count()
        self.served = threading.Event()
        """Set at this robot's first served frame (it is routed and answered)."""
        self._threads = [
            threading.Thread(
                target=self._loop, args=(lane, in_flight), name=f"load-{robot}-{lane}", daemon=True
            )
            for lane in range(in_flight)
        ]

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def join(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        return not any(thread.is_alive() for thread in self._threads)

    def records(self) -> list[FrameRecord]:
        with self._lock:
            return list(self._records)

    def _loop(self, lane: int, lanes: int) -> None:
        stop = self._gen.stopping
        period_s = lanes / self.fps if self.fps else 0.0
        next_at = time.monotonic() + self._phase_s + lane * period_s / lanes
        while not stop.is_set():
            if period_s and stop.wait(max(0.0, next_at - time.monotonic())):
                break
            with self._lock:
                frame = next(self._frames)
            record = self._send(frame)
            with self._lock:
                self._records.append(record)
            if record.outcome is FrameOutcome.SERVED:
                self.served.set()
            elif stop.wait(self._gen.local_s):
                break  # a robot finishes an unserved frame itself before its next one
            if period_s:
                # A reply after the next tick: the frames meanwhile were dropped; go at once.
                next_at = max(next_at + frame_gap_s(period_s, self._poisson), time.monotonic())

    def _send(self, frame: int) -> FrameRecord:
        gen = self._gen
        request = InferRequest(
            robot=self.robot,
            frame=frame,
            model_digest=gen.digest,
            cut=gen.cut,
            tensors=gen.payloads[frame % len(gen.payloads)],
            deadline_s=gen.deadline_s,
            sent_at=time.time(),
        )
        payload = request.to_wire()
        sent = time.monotonic()
        try:
            replies = gen.session.get(self._key, payload=payload, timeout=gen.deadline_s)
            reply = next(iter(replies), None)
            answered = time.monotonic()
            # Read the query to its end (anycast: right after the one reply): a handler dropped
            # before its query is finalized makes Zenoh log an error for the closed channel.
            for _ in replies:
                pass
        except zenoh.ZError as exc:
            return self._record(
                frame, sent, time.monotonic(), FrameOutcome.ERROR, detail=f"zenoh: {exc}"
            )
        if reply is None:
            return self._record(frame, sent, answered, FrameOutcome.NO_ROUTE)
        if reply.ok is None:
            text = reply.err.payload.to_string() if reply.err is not None else ""
            outcome = FrameOutcome.TIMEOUT if "timeout" in text.lower() else FrameOutcome.ERROR
            return self._record(frame, sent, answered, outcome, detail=text)
        try:
            message = decode(reply.ok.payload.to_bytes(), expect=INFER_REPLIES)
        except WireError as exc:
            return self._record(
                frame, sent, answered, FrameOutcome.ERROR, detail=f"bad reply: {exc.reason}"
            )
        if isinstance(message, InferReply):
            return self._record(
                frame,
                sent,
                answered,
                FrameOutcome.SERVED,
                deployment=message.deployment,
                queue_s=message.queue_s,
                compute_s=message.compute_s,
            )
        if isinstance(message, BusyReply):
            return self._record(
                frame, sent, answered, FrameOutcome.BUSY, deployment=message.deployment
            )
        assert isinstance(message, ErrorReply)
        return self._record(frame, sent, answered, FrameOutcome.ERROR, detail=message.code)

    def _record(
        self, frame: int, sent: float, answered: float, outcome: FrameOutcome, **fields: Any
    ) -> FrameRecord:
        return FrameRecord(
            robot=self.robot,
            frame=frame,
            sent_at=sent,
            latency_s=answered - sent,
            outcome=outcome,
            **fields,
        )


class LoadGenerator:
    """Emulated robots `robots` of fleet `cfg`, sending cut `cut` encoded with `codec`.

    `fps` is every robot's frame rate (None: as fast as replies come back), or a mapping per
    robot; `in_flight` the frames each robot keeps in flight (or a mapping). `deadline_s`
    defaults to the fleet's; `local_s` is how long a robot takes to finish a frame the cloud did
    not serve. Robots start at random phases within one frame period (`seed`), as robots
    switched on independently do; `arrivals` is "periodic" (a camera's ticks) or "poisson"
    (exponential gaps of the same mean, drawn from `seed` too).
    """

    def __init__(
        self,
        cfg: FleetConfig,
        robots: Sequence[str],
        *,
        fps: float | dict[str, float | None] | None = 10.0,
        cut: int = 0,
        codec: str = "raw",
        deadline_s: float | None = None,
        in_flight: int | dict[str, int] = 1,
        local_s: float = LOCAL_S,
        seed: int = 0,
        arrivals: str = "periodic",
    ) -> None:
        if not robots:
            raise ValueError("at least one robot is needed")
        if arrivals not in ARRIVALS:
            raise ValueError(f"arrivals must be one of {', '.join(ARRIVALS)}, got {arrivals!r}")
        self.cfg = cfg
        self.cut = cut
        self.codec = codec
        self.deadline_s = deadline_s if deadline_s is not None else cfg.deadline_s
        self.local_s = local_s
        self.digest, self.payloads = cut_payloads(cfg, cut, codec)
        self.stopping = threading.Event()
        self.started_at = math.inf  # set by start()
        # The session and the robots' tokens, released by `close` in reverse (the session last,
        # also when an undeclare fails).
        with contextlib.ExitStack() as owned:
            self.session: zenoh.Session = owned.enter_context(
                open_session(cfg, listen=["tcp/127.0.0.1:0"])
            )
            rng = random.Random(seed)
            self.robots: list[EmulatedRobot] = []
            for robot in robots:
                rate = fps.get(robot) if isinstance(fps, dict) else fps
                lanes = in_flight.get(robot, 1) if isinstance(in_flight, dict) else in_flight
                phase = rng.uniform(0.0, 1.0 / rate) if rate else 0.0
                gaps = random.Random(rng.random()) if arrivals == "poisson" else None
                self.robots.append(
                    EmulatedRobot(self, robot, rate, in_flight=lanes, phase_s=phase, poisson=gaps)
                )
            self._owned = owned.pop_all()

    def __enter__(self) -> LoadGenerator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> LoadGenerator:
        """Declare every robot's liveliness token, then start their frame loops; `started_at`
        is when (monotonic seconds)."""
        self.started_at = time.monotonic()
        for robot in self.robots:
            self._owned.enter_context(
                self.session.liveliness().declare_token(
                    keys.alive_robot(self.cfg.fleet, robot.robot)
                )
            )
        for robot in self.robots:
            robot.start()
        return self

    def wait_served(self, timeout_s: float) -> None:
        """Until every robot has had a frame served (routed and answered); UserError naming
        the robots still waiting after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        for robot in self.robots:
            if not robot.served.wait(max(0.0, deadline - time.monotonic())):
                waiting = [r.robot for r in self.robots if not r.served.is_set()]
                raise UserError(
                    f"no frame of {', '.join(waiting)} was served within {timeout_s:.0f} s "
                    "(is a deployment serving them?)"
                )

    def records(self, since: float = 0.0, until: float = float("inf")) -> list[FrameRecord]:
        """Every robot's frames sent in [since, until) (monotonic seconds)."""
        out = [
            rec for robot in self.robots for rec in robot.records() if since <= rec.sent_at < until
        ]
        return sorted(out, key=lambda rec: rec.sent_at)

    def close(self) -> None:
        """Stop the robots (each finishes its frame in flight), drop the tokens, close."""
        self.stopping.set()
        stuck = [r.robot for r in self.robots if not r.join(self.deadline_s + JOIN_TIMEOUT_S)]
        if stuck:
            log.warning("load generator: %s did not stop in time", ", ".join(stuck))
        self._owned.close()  # the tokens undeclared, then the session closed


def summarize(records: Sequence[FrameRecord], seconds: float) -> dict[str, Any]:
    """Figures of a window of `seconds`: frames and rates by outcome, frames sent and served per
    second, the served frames' latency (median, p95) and each deployment's share of them."""
    frames = len(records)
    counts = {outcome: 0 for outcome in FrameOutcome}
    for rec in records:
        counts[rec.outcome] += 1
    served = [rec for rec in records if rec.outcome is FrameOutcome.SERVED]
    latency = [rec.latency_s for rec in served]
    by_deployment: dict[str, int] = {}
    for rec in served:
        by_deployment[rec.deployment] = by_deployment.get(rec.deployment, 0) + 1

    def rate(outcome: FrameOutcome) -> float:
        return counts[outcome] / frames if frames else 0.0

    return {
        "frames": frames,
        "served": len(served),
        "sent_fps": frames / seconds if seconds > 0 else 0.0,
        "served_fps": len(served) / seconds if seconds > 0 else 0.0,
        "p50_latency_s": statistics.median(latency) if latency else None,
        "p95_latency_s": percentile(latency, 95),
        "p95_queue_s": percentile([rec.queue_s for rec in served], 95),
        "p95_compute_s": percentile([rec.compute_s for rec in served], 95),
        "busy_rate": rate(FrameOutcome.BUSY),
        "timeout_rate": rate(FrameOutcome.TIMEOUT),
        "error_rate": rate(FrameOutcome.ERROR),
        "no_route_rate": rate(FrameOutcome.NO_ROUTE),
        "by_deployment": {
            dep: n / len(served) for dep, n in sorted(by_deployment.items()) if served
        },
    }
