"""`elasticfog robot`: run the robot daemon of one robot of a fleet.

    elasticfog robot --config fleet.yaml --id robot-1 --frames 100 --telemetry robot-1.jsonl

On one host, `--robot-slowdown F` and `--phases FILE.yaml` emulate a slower robot and a changing
uplink (`robotd.emulation`).

The command parses its options, loads the fleet file and runs `robotd.daemon.RobotDaemon` until
`--frames` frames are done or SIGINT/SIGTERM, then prints a summary (`--json`: the same as JSON on
stdout). Logs go to stderr (`common.logs`: level from `--log-level` or `ELASTICFOG_LOG_LEVEL`,
default info). Bad input is one line on stderr and exit code 2.
"""

from __future__ import annotations

import enum
import json
from pathlib import Path
from typing import NoReturn

import typer
from rich.console import Console
from rich.markup import escape

from common.errors import UserError
from common.logs import DEFAULT_LOG_LEVEL, LOG_LEVEL_ENV, LOG_LEVEL_HELP, logging_to_stderr


class Decisions(str, enum.Enum):
    """How the decisions of a robot's services relate (`--decisions`)."""

    JOINT = "joint"
    INDEPENDENT = "independent"


def register(app: typer.Typer) -> None:
    """Add `robot` (and `results`, which follows a robot's results) to the root app."""
    from robotd.results import cli as results_cli

    app.command("robot", help="Run a robot: split each frame between the robot and the cloud.")(
        robot_command
    )
    results_cli.register(app)


def _fail(exc: UserError) -> NoReturn:
    """Bad input: one line on stderr, the error's exit code."""
    # The message as written: a spec like `bag:run:front` holds what Rich would take for an
    # emoji code (`:run:`) or markup (`[...]`).
    Console(stderr=True).print(
        f"[red]error:[/red] {escape(str(exc))}", highlight=False, soft_wrap=True, emoji=False
    )
    raise typer.Exit(exc.exit_code) from None


def _check_policy(policy: str | None) -> str | None:
    """`--policy`, checked before every other option (eager): a typo is what the command says
    first, in one line naming the known policies, also when --config or --id is missing."""
    if policy is not None:
        from robotd.policies import check_policy

        try:
            check_policy(policy, real_time=True)
        except UserError as exc:
            _fail(exc)
    return policy


def robot_command(
    config: Path = typer.Option(..., "--config", help="The fleet file (fleet.yaml)."),
    robot_id: str = typer.Option(..., "--id", help="This robot's id in the fleet file."),
    source: str | None = typer.Option(
        None,
        "--source",
        help="synthetic[:key=F,every=N], photo[:NAME][,motion=M] (real photographs through a "
        "moving camera), video:PATH[,loop=false], bag:PATH[:TOPIC] (a rosbag2 recording), "
        "camera:N|/dev/videoN, a stereo pair for a two-image model: stereo:world, "
        "stereo:motorcycle, stereo:LEFT,RIGHT, zenoh (frames an application publishes on "
        "ef/<fleet>/in/<robot>) or a ROS 2 image topic "
        "ros2:TOPIC[,right=TOPIC][,slop_ms=N][,type=image|compressed][,domain=ID]; default: "
        "the machine's.",
    ),
    frames: int | None = typer.Option(
        None, "--frames", help="Stop after this many frames (default: run until Ctrl-C)."
    ),
    fps: float | None = typer.Option(
        None,
        "--fps",
        help="Frames per second; default: a video's or a bag's own pace, else the machine's "
        "(none: as fast as done).",
    ),
    policy: str | None = typer.Option(
        None,
        "--policy",
        callback=_check_policy,
        is_eager=True,
        help="elastic, ans, neurosurgeon, robot, cloud[:CODEC], static:K[:CODEC], or on "
        "zoo:stereo a navigation option option:N[:CODEC] (e.g. option:1:png); default: the "
        "fleet's.",
    ),
    telemetry: Path | None = typer.Option(
        None, "--telemetry", help="Write one JSON object per frame to this file (JSONL)."
    ),
    uplink_mbit: float | None = typer.Option(
        None,
        "--uplink-mbit",
        help="Pace requests to this many Mbit/s in the application (single-host emulation).",
    ),
    robot_slowdown: float = typer.Option(
        1.0,
        "--robot-slowdown",
        metavar="F",
        help="Emulate a robot F times slower than this host: after each model run the robot "
        "waits (F-1)x the run's time (single-host emulation, see robotd/emulation.py).",
    ),
    phases: Path | None = typer.Option(
        None,
        "--phases",
        help="YAML file of emulation phases (frames, uplink_mbit, slowdown) switched while the "
        "robot runs.",
    ),
    max_in_flight: int | None = typer.Option(
        None,
        "--max-in-flight",
        metavar="N",
        help="Offloaded frames in flight at once (pipelining); default: the machine's (1).",
    ),
    metrics_port: int | None = typer.Option(
        None,
        "--metrics-port",
        metavar="PORT",
        help="Serve Prometheus metrics on this port (/metrics); default: the machine's "
        "metrics.port, else off.",
    ),
    results_ros2: str | None = typer.Option(
        None,
        "--results-ros2",
        metavar="PREFIX",
        help="Publish each frame's outputs on ROS 2 topics PREFIX/<output> (Float32MultiArray; "
        "H×W outputs also as a 32FC1 Image on PREFIX/<output>/image); default: the machine's "
        "results.ros2.",
    ),
    record: Path | None = typer.Option(
        None,
        "--record",
        metavar="OUT.mcap",
        help="Record each applied frame's input (CompressedImage) and outputs (Float32MultiArray, "
        "32FC1 Image) to this MCAP file (any other name: a rosbag2 folder), for ros2 bag play, "
        "Foxglove and MCAP readers.",
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the synthetic and photo frame sources."),
    decisions: Decisions = typer.Option(
        Decisions.JOINT,
        "--decisions",
        help="A robot using several services: 'joint' decisions share the robot's uplink and "
        "CPU by priority (a service gives way where the share the others leave it cannot "
        "carry its frame in time); 'independent': each service's policy is blind to the others.",
    ),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
    log_level: str = typer.Option(
        DEFAULT_LOG_LEVEL, "--log-level", envvar=LOG_LEVEL_ENV, help=LOG_LEVEL_HELP
    ),
) -> None:
    """Run the robot daemon; exits 0 after --frames frames or on SIGINT/SIGTERM."""
    # Heavy imports (pydantic, zenoh, onnxruntime, cv2) where the command runs: `elasticfog --help`
    # must stay fast.
    from common.config import load_fleet
    from common.source_spec import parse_source

    try:
        with logging_to_stderr(log_level):
            # The names first (--policy: `_check_policy`), then the fleet file, before the
            # daemon's imports (zenoh, onnxruntime): a typo fails in well under two seconds.
            parsed_source = None if source is None else parse_source(source)
            cfg = load_fleet(config)
            from robotd.daemon import RobotDaemon, RobotOptions
            from robotd.emulation import check_slowdown, load_phases

            check_slowdown(robot_slowdown)
            loaded = (
                ()
                if phases is None
                else tuple(load_phases(phases, uplink_mbit=uplink_mbit, slowdown=robot_slowdown))
            )
            options = RobotOptions(
                source=parsed_source,
                frames=frames,
                fps=fps,
                policy=policy,
                telemetry=telemetry,
                uplink_mbit=uplink_mbit,
                seed=seed,
                robot_slowdown=robot_slowdown,
                phases=loaded,
                max_in_flight=max_in_flight,
                metrics_port=metrics_port,
                results_ros2=results_ros2,
                record=record,
            )
            from common.keys import Role

            cfg.machine(robot_id, role=Role.ROBOT)  # the id, before the services it uses
            services = cfg.services_of(robot_id)
            if len(services) > 1:
                from robotd.services import RobotServices

                robot = RobotServices(cfg, robot_id, options, joint=decisions is Decisions.JOINT)
                code = robot.run()
                summary, lines = robot.summary_json(), robot.summary_lines()
                abandoned = robot.exit_if_abandoned
            else:
                daemon = RobotDaemon(cfg.for_service(services[0]), robot_id, options)
                code = daemon.run()
                summary, lines = daemon.summary.to_json(), daemon.summary.lines()
                abandoned = daemon.exit_if_abandoned
    except UserError as exc:
        _fail(exc)
    if json_out:
        typer.echo(json.dumps(summary))
    else:
        for line in lines:
            typer.echo(line)
    abandoned(code)
    raise typer.Exit(code)
