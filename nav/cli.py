"""``elasticfog nav ...``: the stereo navigation assistant's commands.

    elasticfog nav disparity left.png right.png --max-disparity 64 --out disparity.npy

Each command parses its options and calls one function; heavy imports (numpy, onnxruntime,
OpenCV) happen inside the command, so ``elasticfog --help`` stays light. Bad input is one line
on stderr and exit code 2.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console

from common.errors import UserError

nav_app = typer.Typer(
    name="nav",
    help="The stereo navigation assistant: stereo disparity, obstacles per curvature.",
    no_args_is_help=True,
)


def register(app: typer.Typer) -> None:
    """Add the `nav` command group to the root app."""
    app.add_typer(nav_app, name="nav")


@nav_app.command("disparity")
def disparity_cmd(
    left: Path = typer.Argument(..., help="Left image of a rectified pair (any size)."),
    right: Path = typer.Argument(..., help="Right image, the same size as the left one."),
    max_disparity: int = typer.Option(
        64, "--max-disparity", help="D: disparities 0..D-1 pixels are searched."
    ),
    out: Path = typer.Option(..., "--out", help="Output .npy: float32 HxW, NaN where invalid."),
    threads: int | None = typer.Option(
        None, "--threads", help="onnxruntime intra-op threads (default: all cores)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print what was written as JSON."),
) -> None:
    """Disparity of a stereo pair in pixels of the left image (the zoo:stereo matcher)."""
    try:
        from nav.disparity import disparity_files

        result = disparity_files(left, right, max_disparity, out, threads)
    except UserError as exc:
        Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(UserError.exit_code) from None
    height, width = result.disparity.shape
    info = {
        "path": str(out),
        "width": width,
        "height": height,
        "max_disparity": max_disparity,
        "valid_share": round(result.valid_share, 4),
        "seconds": round(result.seconds, 3),
    }
    if as_json:
        typer.echo(json.dumps(info, indent=2))
        return
    typer.echo(
        f"wrote {out}: float32 {width}x{height} disparity (0..{max_disparity - 1} px), "
        f"{100 * result.valid_share:.1f}% valid, {result.seconds:.2f} s"
    )


@nav_app.command("assist")
def assist_cmd(
    config: Path = typer.Option(..., "--config", help="The fleet file (fleet.yaml)."),
    robot: str = typer.Option(..., "--robot", help="The robot whose d_coll filters commands."),
    cmd_in: str = typer.Option(
        "/cmd_vel_teleop", "--cmd-in", help="ROS 2 topic of the operator's Twist commands."
    ),
    cmd_out: str = typer.Option(
        "/cmd_vel", "--cmd-out", help="ROS 2 topic the safe Twist commands are published on."
    ),
    results: str | None = typer.Option(
        None,
        "--results",
        metavar="PREFIX",
        help="The robot's ROS 2 results prefix (its d_coll is PREFIX/d_coll); default: the "
        "robot's results.ros2 in the fleet file.",
    ),
    deadline_s: float = typer.Option(
        1.0, "--deadline-s", help="d_coll older than this (s) no longer counts: slow to a stop."
    ),
    deadline_decel: float = typer.Option(
        1.0, "--deadline-decel", help="How fast speed ramps down past the deadline, m/s²."
    ),
    stop_margin: float = typer.Option(
        0.0, "--stop-margin", help="Free distance kept in front of the axle, m."
    ),
    half_width: float = typer.Option(
        0.0,
        "--half-width",
        help="Obstacles this near the path beside it count too, m (half the robot's width; "
        "0: the axle's path only).",
    ),
    stamped: bool = typer.Option(
        False,
        "--stamped",
        help="Commands are geometry_msgs/msg/TwistStamped (Nav2's enable_stamped_cmd_vel, "
        "ros2_control) on --cmd-in and --cmd-out, each safe one with its command's header; "
        "default: geometry_msgs/msg/Twist.",
    ),
) -> None:
    """Filter the operator's cmd_vel with the fleet's d_coll (a ROS 2 safety filter); runs until
    Ctrl-C."""
    import signal
    import threading

    from common.logs import logging_to_stderr
    from nav.assist import run_assist
    from nav.shared_control import AssistantParams

    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with logging_to_stderr("info"):
            params = AssistantParams(
                deadline_s=deadline_s,
                deadline_decel_mps2=deadline_decel,
                stop_margin_m=stop_margin,
                half_width_m=half_width,
            )
            run_assist(
                str(config),
                robot,
                cmd_in,
                cmd_out,
                results_prefix=results,
                params=params,
                stop=stop,
                stamped=stamped,
            )
    except UserError as exc:
        Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(exc.exit_code) from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
