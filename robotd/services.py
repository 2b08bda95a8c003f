"""A robot that uses several services (`elasticfog robot` on a fleet with `services:`): one
process, one capture, one uplink, one CPU, and a frame path per service.

`RobotServices` is the process's daemon. At startup it opens the robot's frame source once (on a
session of its own when the source is fed over Zenoh) and wraps it in a `Capture`, whose feeds
hand each service the newest capture at that service's model input size and fps
(`robotd.sources.capture`). Each service then runs as a `RobotDaemon` of its own on the fleet's
view of that service (`FleetConfig.for_service`: its model or handler, policy, deadline, bound,
results), in a thread: its session, registration, route, anycast key, policy and frame loop are
the service's, while the capture, the emulated uplink (`--uplink-mbit`: one token bucket for
all), the telemetry file (each line names its service) and the robot's liveliness token (the
first service announces it) are shared; `--record PATH` records each service apart
(`NAME.<service>.mcap`), the metrics endpoint is the first service's. A service that no deployment
serves runs on the robot (policy `robot`, with a warning). With a ROS 2 results prefix, each service
publishes under
`<prefix>/<service>`.

The services' decisions share the robot's uplink and CPU (`robotd.shared_budget`).

Stopping: a signal or `stop()` stops every service's daemon, then what this one opened, in
reverse order. A service whose daemon fails to start stops the others and the error is raised.
"""

from __future__ import annotations

import logging
import re
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

from common.config import FleetConfig
from common.daemon import Daemon
from common.errors import UserError
from common.fleet_model import fleet_partition
from common.image_input import ImageInputs
from common.keys import Role
from common.partition import Partition
from common.session import open_session
from common.source_spec import (
    Ros2Spec,
    StereoManeuverSpec,
    StereoPairSpec,
    StereoWorldSpec,
    parse_source,
)
from robotd.daemon import RobotDaemon, RobotOptions
from robotd.frame_path.pacing import TokenBucket
from robotd.results.recorder import MCAP_SUFFIX
from robotd.shared_budget import SharedBudget
from robotd.sources.capture import Capture
from robotd.sources.frame_sources import SourceSession
from robotd.sources.opening import open_source
from robotd.sources.stereo_geometry import ModelCamera, model_camera
from robotd.telemetry import RunSummary, TelemetryFile

log = logging.getLogger("robotd")

START_TIMEOUT_S = 300.0  # a service's model split on first use takes a while
JOIN_TIMEOUT_S = 2.0


class RobotServices(Daemon):
    """`RobotServices(config, robot_id, options)`: see the module docstring. `daemons` holds
    each service's `RobotDaemon` once startup made them."""

    def __init__(
        self,
        config: FleetConfig,
        robot_id: str,
        options: RobotOptions | None = None,
        *,
        joint: bool = True,
    ) -> None:
        super().__init__()
        self.config = config
        self.robot = robot_id
        self.machine = config.machine(robot_id, role=Role.ROBOT)
        self.options = options or RobotOptions()
        self.options.check()
        self.services = config.services_of(robot_id)
        if not self.services:
            raise UserError(f"robot {robot_id!r} uses no service of the fleet")
        self.name = f"robot {robot_id}"
        self.source_spec = parse_source(self.options.source or self.machine.source)
        stereo = isinstance(self.source_spec, StereoWorldSpec | StereoPairSpec | StereoManeuverSpec)
        if stereo or (isinstance(self.source_spec, Ros2Spec) and self.source_spec.right):
            raise UserError(
                f"robot {robot_id}: a stereo source feeds one service; this robot uses "
                f"{len(self.services)} ({', '.join(self.services)})"
            )
        self.views = {name: config.for_service(name) for name in self.services}
        for name in self.services[1:]:
            _listen_anywhere(self.views[name], robot_id)
        self._check_ros2_topics()
        self.budget = SharedBudget(self.views, joint=joint)
        self.daemons: dict[str, RobotDaemon] = {}
        self._threads: list[threading.Thread] = []
        self._errors: dict[str, BaseException] = {}

    def _check_ros2_topics(self) -> None:
        """Two services may not publish on one ROS 2 topic prefix."""
        seen: dict[str, str] = {}
        for name, view in self.views.items():
            prefix = self._ros2_prefix(name, view)
            if prefix is None:
                continue
            if prefix in seen:
                raise UserError(
                    f"services {seen[prefix]} and {name} of robot {self.robot} both publish "
                    f"their results on ROS 2 topic prefix {prefix}"
                )
            seen[prefix] = name

    def _ros2_prefix(self, name: str, view: FleetConfig) -> str | None:
        """Where service `name` publishes on ROS 2: the service's own `results.ros2`, else the
        robot's (`--results-ros2` or the machine's) under `/<service>`."""
        own = view.services[name].results
        if own is not None and own.ros2 is not None:
            return own.ros2
        robot = self.options.results_ros2 or self.machine.results.ros2
        return None if robot is None else f"{robot.rstrip('/')}/{name}"

    # -- what the services are ---------------------------------------------------------------
    @property
    def summaries(self) -> dict[str, RunSummary]:
        return {name: daemon.summary for name, daemon in self.daemons.items()}

    def summary_json(self) -> dict[str, Any]:
        return {
            "robot": self.robot,
            "services": {name: s.to_json() for name, s in self.summaries.items()},
        }

    def summary_lines(self) -> list[str]:
        lines = []
        for name, summary in self.summaries.items():
            lines.append(f"service {name}:")
            lines.extend(f"  {line}" for line in summary.lines())
        return lines

    # -- lifecycle -----------------------------------------------------------------------------
    def startup(self) -> None:
        cfg, options = self.config, self.options
        partitions = {name: fleet_partition(view) for name, view in self.views.items()}
        inputs = {
            name: ImageInputs([part.specs[n] for n in part.inputs], name)
            for name, part in partitions.items()
        }
        height = max(i.height for i in inputs.values())
        width = max(i.width for i in inputs.values())
        session_for_source = None
        if self.source_spec.needs_session:
            session_for_source = self.hold(
                open_session(cfg, machine=self.robot), "zenoh session (frame source)"
            )
        source = self.hold(
            open_source(
                self.source_spec,
                height=height,
                width=width,
                seed=options.seed,
                session=None
                if session_for_source is None
                else SourceSession(session_for_source, cfg, self.robot, stop=self.should_exit),
                built_for=_built_for(partitions, inputs, height, width),
            ),
            "frame source",
        )
        capture = Capture(source)
        telemetry = None
        if options.telemetry is not None:
            telemetry = self.hold(TelemetryFile(options.telemetry), "telemetry file")
        mbit = options.uplink_mbit if options.uplink_mbit is not None else self.machine.uplink_mbit
        uplink = None if mbit is None else TokenBucket.from_mbit(mbit)
        for i, (name, view) in enumerate(self.views.items()):
            service_options = replace(
                options,
                results_ros2=self._ros2_prefix(name, view),
                telemetry=None,
                metrics_port=options.metrics_port if i == 0 else None,
                record=None if options.record is None else service_recording(options.record, name),
            )
            if not view.deployment_ids:
                log.warning(
                    "%s: no deployment serves service %s: the robot runs it itself",
                    self.robot,
                    name,
                )
                service_options = replace(service_options, policy="robot")
            h, w = inputs[name].height, inputs[name].width
            daemon = RobotDaemon(
                view,
                self.robot,
                service_options,
                source=capture.feed(h, w),
                uplink=uplink,
                telemetry_file=telemetry,
                announce_robot=i == 0,
                budget=self.budget.share(name),
            )
            daemon.name = f"robot {self.robot} ({name})"
            self.daemons[name] = daemon
        for name, daemon in self.daemons.items():
            thread = threading.Thread(
                target=self._run_service, args=(name, daemon), name=f"service-{name}"
            )
            thread.start()
            self._threads.append(thread)
        self.on_release(self._stop_services, what="services")
        for (name, daemon), thread in zip(self.daemons.items(), self._threads, strict=True):
            while not daemon.ready.wait(0.1):
                if name in self._errors:
                    raise self._errors[name]
                if self.should_exit.is_set() or not thread.is_alive():
                    return
        log.info(
            "%s: %d services (%s) from one capture (%s)",
            self.robot,
            len(self.daemons),
            ", ".join(self.daemons),
            source.description,
        )

    def _run_service(self, name: str, daemon: RobotDaemon) -> None:
        try:
            daemon.run()
        except BaseException as exc:  # handed to the main thread, which raises it
            self._errors[name] = exc
            self.should_exit.set()

    def main_loop(self) -> None:
        while not self.should_exit.wait(0.1):
            if not any(t.is_alive() for t in self._threads):
                break
        for name, exc in self._errors.items():
            log.error("%s: service %s stopped: %s", self.robot, name, exc)
            raise exc

    def _stop_services(self) -> None:
        for daemon in self.daemons.values():
            daemon.stop()
        for thread in self._threads:
            thread.join(JOIN_TIMEOUT_S)

    def exit_if_abandoned(self, code: int) -> None:
        for daemon in self.daemons.values():
            daemon.exit_if_abandoned(code)
        super().exit_if_abandoned(code)


def service_recording(path: Path, service: str) -> Path:
    """Where `--record PATH` records service `service` of a robot using several: one recording
    (its own topic set) per service, `NAME.<service>.mcap` beside `NAME.mcap` (or
    `PATH.<service>` for a folder)."""
    if path.suffix == MCAP_SUFFIX:
        return path.with_name(f"{path.stem}.{service}{path.suffix}")
    return path.with_name(f"{path.name}.{service}")


def _listen_anywhere(view: FleetConfig, robot: str) -> None:
    """The robot's listen endpoints in service `view` on a port of the system's choosing: each
    service's daemon has a session of its own, and only the first can have the machine's port."""
    machine = view.machines[robot]
    listen = [re.sub(r":\d+(?=$|[?#])", ":0", endpoint) for endpoint in machine.listen]
    view.machines[robot] = machine.model_copy(update={"listen": listen})


def _built_for(
    partitions: dict[str, Partition], inputs: dict[str, ImageInputs], height: int, width: int
) -> ModelCamera | None:
    """The camera the stereo service's model was built for, when one service takes stereo views
    at the capture's size (the source's view is then the model's): a ROS 2 stereo source warns
    when its CameraInfos say another (`robotd.sources.stereo_geometry`)."""
    stereo = [
        name
        for name, i in inputs.items()
        if i.views is not None and (i.height, i.width) == (height, width)
    ]
    if len(stereo) != 1:
        return None
    return model_camera(partitions[stereo[0]].full)
