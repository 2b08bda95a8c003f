"""The robot daemon (`elasticfog robot`): the per-frame split loop, over Zenoh.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Load the split model (one set of shared-weight onnxruntime sessions, every cut warmed up),
   start the low-priority local-run thread, build the policy from a robot-side profile (a source
   fed over the session has no frame yet: raw actions until the frame loop has measured the
   codecs on its first frames, `robotd.robot_profile.FirstFramesRefinement`), return
   the heap memory those runs freed to the system (`common.heap`), open the `--telemetry` file.
2. Open a Zenoh *peer* session connected to the registry endpoint only (the robot's config names
   no cloud host: it finds deployments through the registry's router and queries its anycast
   service key; its ROS 2 node, where it has one, is on a ROS 2 session of its own when
   `ros2.endpoint` is set, `robotd.ros2_node`). Make the result sinks (`robotd.results.sinks`) and
   open the frame source on it
   (`robotd.sources.frame_sources.SourceSession`: a source fed over Zenoh needs the session; every
   source is opened here, so each is released before the session). Declare the telemetry and probe
   publishers, the route subscriber (handled by the registry link), one membership view of the
   registry and the clouds (`common.membership`), and a querier on the service key whose
   matching listener says when a deployment serves it.
3. Start the prober, then announce the liveliness token `alive/robot/<id>`.
4. Wait (bounded, cut short by a signal) for the registry, start the registry link's watcher
   (`robotd.frame_path.registry_link`), then wait for a deployment serving the robot.

Each step hands what it made to the lifecycle (`Daemon.hold`, `on_release`, `announce`), which
releases it all at shutdown in reverse order, the token first, also after a failed startup; the
session is closed explicitly (a session still holding callbacks at exit hangs the process).
Every Zenoh callback is `guarded`: bad input is one throttled line, never a traceback into Zenoh.
`main_loop` runs frames until `--frames`, the source's end or a signal.

A frame's life, from the source to its applied result, is `robotd.frame_path.frame_loop.FrameLoop`'s
(the frame and hedging loop); the daemon makes its parts at startup and calls it.

Beside the daemon: `robotd.frame_path.registry_link.RegistryLink` (registration, the route and its
epoch, reroute requests, the "registry unreachable" reports), `robotd.robot_model` (the split model
loaded at startup, its camera input, cut positions, replies checked against its outputs),
`robotd.frame_path.service_match` (whether a deployment serves the service key),
`robotd.frame_path.request_sender` (the request on the service key, through the emulated uplink),
`robotd.frame_path.frame` (a frame's accounting), `robotd.telemetry_sink` (where each frame's record
and each probe report go),
`robotd.results.sinks` (where each applied frame's result goes: the sinks the robot's config
asks for, made on the session, and any an embedder adds), `robotd.frame_path.failure_runs` (runs of
cloud failures, and when they call for a reroute),
`robotd.robot_profile` (the startup profile and policy) and `robotd.emulation` (on one host: a
robot `--robot-slowdown` times slower than the host, every robot-side model run stretched by a
wait, and `--phases` that change it and the emulated uplink at frame boundaries; the telemetry
file records each frame's phase).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common import keys, rmw_zenoh
from common.config import FleetConfig, check_ros2_session
from common.daemon import Daemon
from common.errors import UserError
from common.heap import release_freed_memory
from common.keys import Role
from common.membership import MemberChange, MembershipView
from common.metrics import MetricsEndpoint, check_port, serve
from common.partition.runtime import SplitModel
from common.session import open_session
from common.source_spec import SourceSpec, check_results_topics, parse_source
from robotd.emulation import (
    Emulation,
    Phase,
    Slowdown,
    check_slowdown,
    emulation_note,
    scaled_profile,
)
from robotd.frame_path.frame import FrameResult
from robotd.frame_path.frame_loop import FrameLoop
from robotd.frame_path.local_runs import LocalRunner
from robotd.frame_path.model_runs import ModelRuns
from robotd.frame_path.pacing import FramePacer, TimelinePacer, TokenBucket
from robotd.frame_path.probes import PROBE_INTERVAL_S, CloudTime, RobotProber, probe_padding_bytes
from robotd.frame_path.registry_link import REGISTRY_RETRY_INITIAL_S, RegistryLink
from robotd.frame_path.request_sender import RequestSender
from robotd.frame_path.service_match import ServiceMatch
from robotd.frame_path.video_streams import VideoEncoders
from robotd.metrics import RobotMetrics
from robotd.policies import Objective, Policy
from robotd.results.sinks import ResultSink, open_result_sinks
from robotd.robot_model import RobotModel, open_split_model
from robotd.robot_profile import FirstFramesRefinement, build_policy, robot_profile, warm_up
from robotd.shared_budget import ServiceShare
from robotd.sources.frame_sources import FrameSource, SourceSession
from robotd.telemetry import RunSummary, TelemetryFile
from robotd.telemetry_sink import TelemetrySink

# `robot_profile` is imported from here by the benchmarks (it lived in this module).
__all__ = ["FrameResult", "RobotDaemon", "RobotOptions", "robot_profile"]

log = logging.getLogger("robotd")

# How long startup waits for the registry's token, then for a deployment serving the robot, so
# the first frames are not finished locally only because the session was still meeting peers.
REGISTRY_WAIT_S = 2.0
ROUTE_WAIT_S = 3.0


@dataclass
class RobotOptions:
    """Run options of the robot daemon; None takes the machine's value from fleet.yaml."""

    source: str | SourceSpec | None = None
    frames: int | None = None
    fps: float | None = None
    policy: str | None = None
    telemetry: Path | None = None
    uplink_mbit: float | None = None
    seed: int = 0
    probe_interval_s: float = PROBE_INTERVAL_S
    probe_padding_bytes: int | None = None
    registry_wait_s: float = REGISTRY_WAIT_S
    route_wait_s: float = ROUTE_WAIT_S
    robot_slowdown: float = 1.0
    phases: tuple[Phase, ...] = ()
    max_in_flight: int | None = None
    metrics_port: int | None = None  # None: the machine's `metrics.port` (off if unset)
    # ROS 2 topic prefix of the results (`results: {ros2: ...}`); None: the machine's.
    results_ros2: str | None = None
    # `--record`: each applied frame's input and result written to this MCAP file (or folder).
    record: Path | None = None

    @property
    def initial_slowdown(self) -> float:
        """The emulated slowdown of the first frames (the first phase's, if any)."""
        return self.phases[0].slowdown if self.phases else self.robot_slowdown

    def check(self) -> None:
        """UserError naming the first bad option."""
        if self.frames is not None and self.frames < 1:
            raise UserError(f"--frames must be at least 1, got {self.frames}")
        if self.fps is not None and not (self.fps > 0 and np.isfinite(self.fps)):
            raise UserError(f"--fps must be a positive number, got {self.fps}")
        if self.uplink_mbit is not None and not (
            self.uplink_mbit > 0 and np.isfinite(self.uplink_mbit)
        ):
            raise UserError(f"--uplink-mbit must be a positive number, got {self.uplink_mbit}")
        if self.probe_interval_s <= 0:
            raise UserError(f"probe interval must be > 0 s, got {self.probe_interval_s}")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise UserError(f"--max-in-flight must be at least 1, got {self.max_in_flight}")
        check_slowdown(self.robot_slowdown)
        check_port(self.metrics_port)
        if self.record is not None:
            from robotd.results.recorder import check_record_path

            check_record_path(self.record)


@dataclass(frozen=True)
class _Started:
    """What startup made that the frame loop, the callbacks and shutdown use."""

    model: SplitModel
    link: RegistryLink
    loop: FrameLoop


class RobotDaemon(Daemon):
    """`elasticfog robot` for one service: `config` is a one-service fleet or a service's view
    (`FleetConfig.for_service`). `policy` and `on_result` let tests replace the policy and see
    each frame's outputs; `__init__` does no I/O.

    A robot using several services runs one daemon per service in one process
    (`robotd.services.RobotServices`), which hands each its share of what they have in common:
    `source` (the service's feed of the robot's one capture: not opened or closed here),
    `uplink` (the one emulated uplink they share), `telemetry_file` (one file for all) and
    `announce_robot` (only one of them announces the robot's token) and `budget` (the service's
    share of the robot's uplink and CPU, `robotd.shared_budget`: it wraps the policy)."""

    name = "robot"

    def __init__(
        self,
        config: FleetConfig,
        robot_id: str,
        options: RobotOptions | None = None,
        *,
        policy: Policy | None = None,
        on_result: Callable[[FrameResult], None] | None = None,
        source: FrameSource | None = None,
        uplink: TokenBucket | None = None,
        telemetry_file: TelemetryFile | None = None,
        announce_robot: bool = True,
        budget: ServiceShare | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.service = config.service_name
        self._given_source = source
        self._given_uplink = uplink
        self._given_telemetry = telemetry_file
        self._announce_robot = announce_robot
        self._budget = budget
        self.machine = config.machine(robot_id, role=Role.ROBOT)
        self.robot = robot_id
        self.options = options or RobotOptions()
        self.options.check()
        self.fleet = config.fleet
        self.deadline_s = config.deadline_s
        self.source_spec = parse_source(self.options.source or self.machine.source)
        self.fps = self.options.fps if self.options.fps is not None else self.machine.fps
        mbit = self.options.uplink_mbit
        self.uplink_mbit = mbit if mbit is not None else self.machine.uplink_mbit
        self.policy_spec = self.options.policy or config.policy.kind
        results_ros2 = self.options.results_ros2 or self.machine.results.ros2
        self.results_ros2 = None if results_ros2 is None else rmw_zenoh.topic_name(results_ros2)
        check_results_topics(
            self.source_spec, self.results_ros2, config.ros2_for(robot_id).domain()
        )
        check_ros2_session(config, robot_id, self.source_spec, self.results_ros2)
        self.name = f"robot {robot_id}"
        self.summary = RunSummary(robot_id)
        self._policy_override = policy
        self._on_result = on_result
        self._objective = Objective.parse(config.objective.model_dump())
        self._svc_key = keys.svc_infer(self.fleet, config.service_name, robot_id)
        self._served = ServiceMatch()
        self._cloud_time = CloudTime()
        # Offloaded frames in flight at once (`robotd.frame_path.pipeline`).
        self.max_in_flight = self.options.max_in_flight or self.machine.max_in_flight
        # Publications, file and summary of the frames; what they go to is made in startup.
        self._sink = TelemetrySink(robot_id, self.summary, self.service)
        # Where each applied frame's result goes (`robotd.results.sinks`), in the lifecycle.
        self._result_sinks: list[ResultSink] = []
        # Emulation (`robotd.emulation`): every robot-side model run goes through the slowdown;
        # phases switch it and the uplink at frame boundaries.
        self._slowdown = Slowdown(self.options.initial_slowdown, stop=self.should_exit)
        self.metrics: MetricsEndpoint | None = None  # `/metrics`, when its port is set
        # Made in startup and released by the lifecycle; what the frame loop, the callbacks and
        # shutdown use is one `_Started`, set once the frame loop is made (`_parts`). A callback
        # declared before then is handed the part it needs.
        self._started: _Started | None = None

    # -- what startup made -----------------------------------------------------------------
    @property
    def _parts(self) -> _Started:
        """The started parts (RuntimeError before startup has made the frame loop)."""
        if self._started is None:
            raise RuntimeError("the robot is not started")
        return self._started

    @property
    def model(self) -> SplitModel:
        """The split model (after startup)."""
        return self._parts.model

    @property
    def policy(self) -> Policy:
        """The split policy (after startup): the frame loop's, which the one measured on the
        first frames replaces when the source had none at start."""
        return self._parts.loop.policy

    @property
    def loop(self) -> FrameLoop:
        """The frame loop (after startup)."""
        return self._parts.loop

    @property
    def link(self) -> RegistryLink:
        """The link to the registry (after startup)."""
        return self._parts.link

    # -- public ----------------------------------------------------------------------------
    @property
    def frames_done(self) -> int:
        """Frames finished and recorded so far."""
        return self._started.loop.frames_done if self._started is not None else 0

    @property
    def route(self) -> tuple[str | None, int]:
        """The deployment the registry last said serves this robot, and its epoch."""
        return self._started.link.route if self._started is not None else (None, 0)

    def _frame_source(self) -> FrameSource | None:
        """The frame source once the frame loop holds it (the metrics read its counts)."""
        return self._started.loop.source if self._started is not None else None

    @property
    def result_sinks(self) -> tuple[ResultSink, ...]:
        """The sinks each applied frame's result is published to, in the order added."""
        return tuple(self._result_sinks)

    def add_result_sink(self, sink: ResultSink, what: str = "result sink") -> ResultSink:
        """Publish every applied frame's result to `sink` from now on; the lifecycle takes it
        off the list and closes it at shutdown (in reverse order with the rest)."""
        self._result_sinks.append(sink)

        def release() -> None:
            if sink in self._result_sinks:
                self._result_sinks.remove(sink)
            sink.close()

        self.on_release(release, what=what)
        return sink

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        cfg = self.config
        self.metrics = serve(
            self, self.machine.metrics, self.options.metrics_port, who=f"robot {self.robot}"
        )
        if self.metrics is not None:
            self._sink.metrics = RobotMetrics(
                self.metrics.registry, self.robot, lambda: self.route, source=self._frame_source
            )
        model = self.hold(open_split_model(cfg, self.machine, who=self.robot), "model sessions")
        robot_model = RobotModel(model, cfg.runs)
        warm_up(model, robot_model.sample_feeds)
        local = LocalRunner(f"local-run-{self.robot}")
        local.start()
        self.on_release(local.stop, what="local-run thread")
        policy, refinement = self._policy_override, None
        if policy is None:
            policy, refinement = self._start_policy(robot_model)
        # The runs above (warm-up, profile, codec calibration) leave their freed tensors resident.
        release_freed_memory(self.robot)
        if self._given_telemetry is not None:
            self._sink.file = self._given_telemetry
        elif self.options.telemetry is not None:
            self._sink.file = self.hold(TelemetryFile(self.options.telemetry), "telemetry file")
        source, requests, link, emulation = self._open_zenoh(model, robot_model)
        loop = FrameLoop(
            robot=self.robot,
            model=model,
            robot_model=robot_model,
            policy=policy,
            objective=self._objective,
            deadline_s=self.deadline_s,
            source=source,
            requests=requests,
            link=link,
            runs=ModelRuns(self._slowdown, local),
            local=local,
            slowdown=self._slowdown,
            emulation=emulation,
            sink=self._sink,
            summary=self.summary,
            cloud_time=self._cloud_time,
            stop=self.should_exit,
            throttled=self.throttled,
            max_in_flight=self.max_in_flight,
            result_sinks=self._result_sinks,
            on_result=self._on_result,
            refinement=refinement,
            video=VideoEncoders(crf=cfg.video.crf),
        )
        self._started = _Started(model=model, link=link, loop=loop)
        log.info(
            "%s: model %s (%d cuts, digest %s), policy %s, source %s, deadline %.3f s, "
            "registry %s%s%s",
            self.robot,
            cfg.runs,
            model.num_cuts,
            model.digest[:12],
            policy.name,
            source.description,
            self.deadline_s,
            cfg.registry.endpoint,
            f", {self.max_in_flight} frames in flight" if self.max_in_flight > 1 else "",
            # Phases describe themselves as they start.
            "" if self.options.phases else emulation_note(self.uplink_mbit, self._slowdown.factor),
        )
        warn_if_refused_past_limit(self.config, self.robot, self.max_in_flight)
        self._wait_for_fleet()

    def _start_policy(self, robot_model: RobotModel) -> tuple[Policy, FirstFramesRefinement | None]:
        """The policy built on this robot's profile and, when its codecs are to be measured on
        the first frames it serves (a source fed over the session), what then rebuilds it."""
        cfg = self.config
        start = robot_model.profile(
            cfg,
            source_spec=self.source_spec,
            seed=self.options.seed,
            threads=self.machine.threads,
            policy_spec=self.policy_spec,
        )
        profile = scaled_profile(start.profile, self._slowdown.factor)

        def build(profile: dict[str, Any]) -> Policy:
            policy = build_policy(self.policy_spec, cfg, profile, self._objective)
            return policy if self._budget is None else self._budget.wrap(policy)

        if start.first_frames is None:
            return build(profile), None
        refinement = FirstFramesRefinement(
            start.first_frames,
            profile,
            build,
            count=cfg.fidelity.calibration_frames,
            robot=self.robot,
        )
        return build(profile), refinement

    def _open_zenoh(
        self, model: SplitModel, robot_model: RobotModel
    ) -> tuple[FrameSource, RequestSender, RegistryLink, Emulation]:
        """The session and what is made on it; the token is announced last."""
        cfg = self.config
        session = self.hold(open_session(cfg, machine=self.robot), "zenoh session")
        for sink, what in open_result_sinks(cfg, self.robot, session):
            self.add_result_sink(sink, what)
        if self.results_ros2 is not None:
            from robotd.results.ros2 import Ros2ResultSink  # rosbags only where it is used

            ros2_sink = Ros2ResultSink(
                cfg,
                self.robot,
                session,
                self.results_ros2,
                height=robot_model.inputs.height,
                width=robot_model.inputs.width,
            )
            self.add_result_sink(ros2_sink, f"ROS 2 results {self.results_ros2}")
        if self.options.record is not None:
            from robotd.results.recorder import McapRecorder  # rosbags only where it is used

            recorder = McapRecorder(
                self.options.record,
                self.robot,
                robot_model.inputs,
                results_ros2=self.results_ros2,
            )
            self.add_result_sink(recorder, f"recording {self.options.record}")
        if self._given_source is not None:
            source = self._given_source  # the robot's capture, shared with its other services
        else:
            # Opened on the session (a source fed over Zenoh needs it), so released before it.
            source = self.hold(
                robot_model.open_source(
                    self.source_spec,
                    seed=self.options.seed,
                    session=SourceSession(session, cfg, self.robot, stop=self.should_exit),
                ),
                "frame source",
            )
        uplink = self._given_uplink
        if uplink is None and self.uplink_mbit is not None:
            uplink = TokenBucket.from_mbit(self.uplink_mbit)
        requests = RequestSender(
            session,
            self._svc_key,
            robot=self.robot,
            model_digest=model.digest,
            deadline_s=self.deadline_s,
            max_reply_bytes=cfg.max_payload_bytes,
            uplink=uplink,
            member_key=functools.partial(
                keys.svc_infer_at, self.fleet, cfg.service_name, self.robot
            ),
            served=self._served.wait_served,
        )

        def set_uplink(bucket: TokenBucket | None) -> None:
            """A phase's emulated uplink (None: requests are not paced)."""
            requests.uplink = bucket

        emulation = Emulation(self.options.phases, self._slowdown, set_uplink, robot=self.robot)
        link = RegistryLink(
            session,
            cfg,
            self.robot,
            model_digest=model.digest,
            throttled=self.throttled,
            guard=self.guarded,
            max_in_flight=self.max_in_flight,
        )
        self._sink.declare(self, session, self.fleet)
        route_key = keys.route(self.fleet, self.robot)
        self.hold(
            session.declare_subscriber(
                route_key, self.guarded(link.on_route, what=f"a message on {route_key}")
            ),
            "route subscriber",
        )
        members = self.hold(
            MembershipView(
                session,
                self.fleet,
                roles=("registry", "cloud"),
                on_change=self.guarded(
                    functools.partial(self._on_member, link), what="a membership change"
                ),
            ),
            "membership view",
        )
        # A querier on the service key only to be told when a deployment serves it (frames use
        # session.get: each has its own timeout).
        self._served.declare(self, session, self._svc_key)
        padding = self.options.probe_padding_bytes
        if padding is None:
            padding = probe_padding_bytes([c.bytes for c in model.partition.cuts])
        prober = RobotProber(
            session,
            self.fleet,
            self.robot,
            max_padding_bytes=padding,
            publish=self._sink.probe,
            # Not those the fleet file says do not serve this service.
            alive_deployments=lambda: set(members.ids("cloud")) - cfg.not_serving,
            cloud_time=self._cloud_time,
            interval_s=self.options.probe_interval_s,
            max_reply_bytes=cfg.max_payload_bytes,
            service=self.service,
        )
        prober.start()
        self.on_release(prober.stop, what="prober")
        # Ready: announce the robot last; the lifecycle takes the token down first at shutdown.
        if self._announce_robot:
            token = session.liveliness().declare_token(keys.alive_robot(self.fleet, self.robot))
            self.announce(token)
        return source, requests, link, emulation

    def _wait_for_fleet(self) -> None:
        """Give the session a moment to meet the registry and the deployment serving this robot
        (bounded, and cut short by a signal; frames are finished locally meanwhile anyway), then
        leave the registry to the link's watcher thread."""
        link = self.link
        reachable = link.wait_reachable(self.options.registry_wait_s, self.should_exit)
        if not reachable:
            link.report_unreachable("", REGISTRY_RETRY_INITIAL_S)
        link.start(reported=not reachable)
        self.on_release(link.stop, what="registry watcher")
        if reachable and not self._served.wait(self.options.route_wait_s, self.should_exit):
            log.info(
                "%s: no deployment serves %s yet; frames are finished on the robot until one does",
                self.robot,
                self._svc_key,
            )

    def shutdown(self) -> None:
        """Let go of a hedged frame's reply still awaited (it may be waiting for the emulated
        uplink), then release everything startup made: the token first, then in reverse."""
        if self._started is not None:
            self._started.loop.cancel()  # a hedged frame's reply awaited, frames in flight
        super().shutdown()

    # -- callbacks -------------------------------------------------------------------------
    def _on_member(self, link: RegistryLink, change: MemberChange) -> None:
        if change.role == Role.REGISTRY:
            link.registry_changed(bool(change.alive_ids))

    # -- the frame loop (`robotd.frame_path.frame_loop`)
    # ---------------------------------------------
    def main_loop(self) -> None:
        self.loop.run(frames=self.options.frames, fps=self.fps, pacer=self._pacer())

    def _pacer(self) -> FramePacer | TimelinePacer | None:
        """The source's own timeline (a bag's, a video file's) unless --fps is given; None: the
        fps (the machine's, none: as fast as frames complete)."""
        if self.options.fps is None and self.loop.source.next_offset_s() is not None:
            log.info("%s: frames at the source's own pace", self.robot)
            return TimelinePacer(self.loop.source.next_offset_s)
        return None


def warn_if_refused_past_limit(config: FleetConfig, robot: str, max_in_flight: int) -> None:
    """A robot with more frames in flight than a deployment admits per robot gets `busy` there
    for the rest (finished on the robot: nothing is lost, but the overlap is not)."""
    short = config.short_of_in_flight(max_in_flight)
    if short:
        log.warning(
            "%s: %d frames in flight, but %s admit(s) fewer of one robot's requests at once "
            "(batching.max_in_flight_per_robot): frames past that are answered busy there "
            "and finished here",
            robot,
            max_in_flight,
            ", ".join(f"{c} ({limit})" for c, limit in short.items()),
        )
