"""`elasticfog bench ...`: the papers' experiments on the namespace testbed (root).

Each command parses its options and calls one experiment of `deploy/experiments` (see
docs/experiments.md): it brings a testbed up, runs the real daemons inside its hosts, shapes the
robot's uplink or CPU quota while the robot streams, prints a markdown table on stdout (or
`--json`), writes PNG plots into docs/img/, and always removes the testbed again, also on Ctrl-C.
Progress goes to stderr. `--quick` runs short. `--tls` runs every fleet with mutual TLS and the
access control on (certificates made per run with the hosts' testbed addresses; the JSON says
`"tls": true`).

`scale` is the exception: it runs on loopback without root (a registry and cloud daemons as
subprocesses, emulated robots from a load generator; see docs/scale.md).
"""

from __future__ import annotations

import functools
import inspect
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import typer
from rich.console import Console

from common.defaults import DEFAULT_CAMERA_SOURCE
from common.errors import UserError
from experiments import scale_defaults
from experiments.defaults import DEFAULT_INPUT_SHAPE, DEFAULT_MODEL, DEFAULT_ROBOT_CPU

bench_app = typer.Typer(
    name="bench",
    help="The papers' experiments on the namespace testbed (root): tables and plots.",
    no_args_is_help=True,
)

INTERRUPTED_EXIT_CODE = 130
REPO_ROOT = Path(__file__).resolve().parents[1]
# In a source checkout the plots go beside the docs that show them; elsewhere into the current
# directory.
DEFAULT_PLOTS_DIR = (
    REPO_ROOT / "docs" / "img" if (REPO_ROOT / "docs").is_dir() else Path("elasticfog-plots")
)

QUICK_OPTION = typer.Option(False, "--quick", help="A short run (fewer frames).")
FRAMES_OPTION = typer.Option(
    None, "--frames", help="Frames per robot run (default: the experiment's, less with --quick)."
)
ROBOT_CPU_OPTION = typer.Option(
    DEFAULT_ROBOT_CPU,
    "--robot-cpu",
    help="The robot host's CPU quota, in cores (how slow the robot is).",
)
MODEL_OPTION = typer.Option(DEFAULT_MODEL, "--model", help="zoo:NAME or an ONNX file.")
SHAPE_OPTION = typer.Option(
    None,
    "--input-shape",
    help=f"Camera image CxHxW. Default: {'x'.join(map(str, DEFAULT_INPUT_SHAPE))} for a zoo model "
    "(which takes it as uint8 1xHxWxC) and for a file's dynamic dimensions; a file whose "
    "dimensions are fixed has its own shape.",
)
PLOTS_OPTION = typer.Option(DEFAULT_PLOTS_DIR, "--plots-dir", help="Where PNG plots are written.")
NO_PLOTS_OPTION = typer.Option(False, "--no-plots", help="Write no plots.")
WORKDIR_OPTION = typer.Option(
    None, "--workdir", help="Keep fleets, telemetry and daemon logs here (default: temporary)."
)
NAME_OPTION = typer.Option(None, "--name", help="Testbed name (default: one of its own).")
JSON_OPTION = typer.Option(False, "--json", help="Print plain JSON on stdout.")
TLS_OPTION = typer.Option(
    False,
    "--tls",
    help="Mutual TLS and access control on every link (as `elasticfog init --tls`; "
    "certificates carry the testbed addresses).",
)
SOURCE_OPTION = typer.Option(
    DEFAULT_CAMERA_SOURCE,
    "--source",
    help="The robot's camera: photo[:NAME][,motion=pan|zoom|shake|mixed][,speed=F] or "
    "synthetic[...] (e.g. photo:astronaut,motion=pan: a panning camera, as video codes it).",
)
POLICY_VARIANTS_HELP = (
    "elastic-nohedge: elastic without hedged exploration; elastic-h264: elastic with h264 "
    "video among the camera image's codecs (fidelity.video); elastic-h264only: with h264 its "
    "only lossy codec"
)
TLS_NOTE = "Every link: mutual TLS with access control (`--tls`)."

# An experiment's result: a typed one, or (the experiments not typed yet) its JSON object.
Result = TypeVar("Result")

# The options every testbed experiment takes (`testbed_command`), in their order in --help:
# name -> (annotation, typer option). `as_json` is the command's; the others make BenchOptions.
SHARED_OPTIONS: dict[str, tuple[Any, Any]] = {
    "quick": (bool, QUICK_OPTION),
    "frames": (int | None, FRAMES_OPTION),
    "robot_cpu": (float, ROBOT_CPU_OPTION),
    "model": (str, MODEL_OPTION),
    "input_shape": (str | None, SHAPE_OPTION),
    "plots_dir": (Path, PLOTS_OPTION),
    "no_plots": (bool, NO_PLOTS_OPTION),
    "workdir": (Path | None, WORKDIR_OPTION),
    "name": (str | None, NAME_OPTION),
    "tls": (bool, TLS_OPTION),
    "as_json": (bool, JSON_OPTION),
}


def register(app: typer.Typer) -> None:
    """Add the `bench` command group to the root app."""
    app.add_typer(bench_app, name="bench")


def _options(
    *,
    quick: bool,
    frames: int | None,
    robot_cpu: float,
    model: str,
    input_shape: str | None,
    plots_dir: Path,
    no_plots: bool,
    workdir: Path | None,
    name: str | None,
    tls: bool = False,
) -> Any:
    """The experiment's options; bad ones are reported (one line, exit 2)."""
    from common.zoo import parse_shape
    from deploy.testbed import check_name
    from experiments.options import BenchOptions

    try:
        if name is not None:
            check_name(name)
        err = Console(stderr=True)
        options = BenchOptions(
            model=model,
            input_shape=() if input_shape is None else parse_shape(input_shape),
            robot_cpu=robot_cpu,
            frames=frames,
            quick=quick,
            workdir=workdir,
            plots_dir=None if no_plots else plots_dir,
            name=name,
            log=lambda message: err.print(f"[dim]bench:[/dim] {message}", highlight=False),
            tls=tls,
        )
        options.check()
    except UserError as exc:
        _fail(exc)
    return options


def testbed_command(
    name: str, *, fixed: dict[str, Any] | None = None
) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Register `fn(options, as_json, **its own options)` as `elasticfog bench NAME`, with the
    shared options (`SHARED_OPTIONS`) after its own: the command declares only what is its own
    and gets one checked `BenchOptions`. `fixed`: shared options this command does not offer,
    with the value they take (anycast's robot is not slowed: robot_cpu 1)."""
    fixed = fixed or {}

    def register(fn: Callable[..., None]) -> Callable[..., None]:
        own = [
            p
            for p in inspect.signature(fn).parameters.values()
            if p.name not in ("options", "as_json")
        ]
        shared = [
            inspect.Parameter(key, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=tp)
            for key, (tp, option) in SHARED_OPTIONS.items()
            if key not in fixed
        ]

        @functools.wraps(fn)
        def command(**given: Any) -> None:
            values = {key: given.pop(key) for key in SHARED_OPTIONS if key in given}
            as_json = values.pop("as_json")
            fn(options=_options(**{**values, **fixed}), as_json=as_json, **given)

        command.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
            [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own] + shared
        )
        bench_app.command(name)(command)
        return fn

    return register


def _run(
    options: Any,
    experiment: Callable[[], Result],
    render: Callable[[Result], str],
    plot: Callable[[Result, Path], list[Path]],
    as_json: bool,
    public: Callable[[Result], dict[str, Any]],
    tls_key: bool = True,
) -> None:
    """Run, plot, print. `public`: the result's `--json` object; `tls_key`: the JSON says
    whether TLS was on (False: a contract that allows no key beyond its own)."""
    from deploy.testbed import require_root

    err = Console(stderr=True)
    try:
        require_root()  # after every option was checked: bad input is reported to anyone
        result = experiment()
    except UserError as exc:
        _fail(exc)
    except KeyboardInterrupt:
        err.print("interrupted; the testbed and every daemon are gone", highlight=False)
        raise typer.Exit(INTERRUPTED_EXIT_CODE) from None
    data = public(result)
    if options.plots_dir is not None and data.get("results"):
        for path in plot(result, options.plots_dir):
            err.print(f"plot: {path}", highlight=False)
    if as_json:
        extra = {"tls": options.tls} if tls_key else {}
        typer.echo(json.dumps({**data, **extra}))
    else:
        typer.echo(render(result))
        if options.tls:
            typer.echo(f"\n{TLS_NOTE}")


def _as_is(result: dict[str, Any]) -> dict[str, Any]:
    """The `--json` of an experiment whose result is its JSON object."""
    return result


def _fail(exc: UserError) -> NoReturn:
    """Report bad input or a failed run in one line and exit with its code."""
    Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
    raise typer.Exit(exc.exit_code) from None


def _guard(fn: Callable[[], Any]) -> Any:
    try:
        return fn()
    except UserError as exc:
        _fail(exc)


def _use_source(options: Any, source: str) -> None:
    """`--source` of a single-edge experiment, checked, into its options."""
    from experiments.options import check_source

    _guard(lambda: check_source(source))
    options.source = source


def _policies(text: str) -> list[str]:
    """`--policies`, checked against the policies the robot runs."""
    from experiments.options import parse_names
    from robotd.policies import policy_names

    known = list(policy_names(real_time=True))
    return _guard(lambda: parse_names(text, "--policies", known))


@testbed_command("table1")
def table1(
    options: Any,
    as_json: bool,
    uplinks: str = typer.Option(
        "0.5,1,2,5,20", "--uplinks", help="Robot uplink caps in Mbit/s, comma-separated."
    ),
    policies: str = typer.Option(
        "robot,cloud,cloud:jpeg80,elastic,elastic-nohedge,neurosurgeon,ans",
        "--policies",
        help=f"Policies, comma-separated ({POLICY_VARIANTS_HELP}).",
    ),
    repeat: int = typer.Option(
        1,
        "--repeat",
        min=1,
        help="Runs per cell, the policies alternated in each round; a cell reports its run "
        "with the median mean latency (a shared host's noise moves one run by a tenth).",
    ),
    source: str = SOURCE_OPTION,
) -> None:
    """ElasticROS Table I: latency, robot CPU and energy per frame at each uplink cap."""
    from experiments import table1 as t1
    from experiments.options import parse_floats

    _use_source(options, source)
    caps = _guard(lambda: parse_floats(uplinks, "--uplinks"))
    names = _policies(policies)
    _run(
        options,
        lambda: t1.run(options, caps, names, repeat),
        t1.markdown,
        t1.plot,
        as_json,
        t1.Table1Result.public,
    )


@testbed_command("glitch")
def glitch(
    options: Any,
    as_json: bool,
    from_mbit: float = typer.Option(..., "--from-mbit", help="Uplink cap before, Mbit/s."),
    to_mbit: float = typer.Option(..., "--to-mbit", help="Uplink cap after, Mbit/s."),
    policies: str = typer.Option(
        "elastic,elastic-nohedge,cloud:jpeg80,cloud,robot",
        "--policies",
        help=f"Comma-separated ({POLICY_VARIANTS_HELP}).",
    ),
    source: str = SOURCE_OPTION,
) -> None:
    """A bandwidth glitch while the robot streams: before / on / after, frames to settle."""
    from experiments import glitch as gl
    from experiments.options import parse_floats

    _use_source(options, source)
    a, b = _guard(lambda: parse_floats(f"{from_mbit},{to_mbit}", "--from-mbit/--to-mbit"))
    names = _policies(policies)
    _run(
        options,
        lambda: gl.run(options, a, b, names),
        gl.markdown,
        lambda r, d: gl.plot(r, d, "glitch"),
        as_json,
        gl.GlitchResult.public,
    )


@testbed_command("table2")
def table2(
    options: Any,
    as_json: bool,
    policies: str = typer.Option(
        "elastic,elastic-nohedge,cloud:jpeg80,cloud,robot",
        "--policies",
        help=f"Comma-separated ({POLICY_VARIANTS_HELP}).",
    ),
    source: str = SOURCE_OPTION,
) -> None:
    """ElasticROS Table II: the glitches 10→3, 5→1 and 10→1 Mbit/s."""
    from experiments import glitch as gl

    _use_source(options, source)
    names = _policies(policies)
    _run(
        options,
        lambda: gl.run_table2(options, gl.TABLE2_GLITCHES, names),
        gl.markdown,
        lambda r, d: gl.plot(r, d, "table2"),
        as_json,
        gl.GlitchResult.public,
    )


@testbed_command("table3")
def table3(
    options: Any,
    as_json: bool,
    policies: str = typer.Option(
        "elastic,elastic-nohedge,robot,cloud:jpeg80,cloud",
        "--policies",
        help=f"Comma-separated ({POLICY_VARIANTS_HELP}).",
    ),
    source: str = SOURCE_OPTION,
) -> None:
    """ElasticROS Table III: the robot's CPU quota drops to --robot-cpu, then recovers."""
    from experiments import table3 as t3

    _use_source(options, source)
    names = _policies(policies)
    _run(
        options,
        lambda: t3.run(options, names),
        t3.markdown,
        t3.plot,
        as_json,
        t3.Table3Result.public,
    )


@testbed_command("anycast", fixed={"robot_cpu": 1.0})
def anycast(
    options: Any,
    as_json: bool,
) -> None:
    """FogROS2-LS Table I: deadline misses with 1-4 deployments when edge-1 is slowed."""
    from experiments import anycast as ac

    _run(options, lambda: ac.run(options), ac.markdown, ac.plot, as_json, _as_is)


@testbed_command(
    "services",
    fixed={"model": DEFAULT_MODEL, "input_shape": None, "frames": None, "tls": False},
)
def services(
    options: Any,
    as_json: bool,
    rounds: int | None = typer.Option(
        None,
        "--rounds",
        help="Rounds, each a joint and an independent run (default 3, 1 with --quick).",
    ),
    fps: float = typer.Option(5.0, "--fps", help="Frames per second of every service."),
    uncontended_mbit: float = typer.Option(
        20.0, "--uncontended-mbit", help="The robot's uplink cap in the first phase, Mbit/s."
    ),
    contended_mbit: float = typer.Option(
        2.0, "--contended-mbit", help="The cap the uplink drops to for the second phase, Mbit/s."
    ),
    phase_s: float | None = typer.Option(
        None, "--phase-s", help="Seconds of each phase (default 20, 8 with --quick)."
    ),
    handler_policy: str = typer.Option(
        "cloud:jpeg90",
        "--handler-policy",
        help="The handler service's policy (the networks' is elastic): cloud:jpeg90 (always the "
        "deployment, as FogROS2-LS serves AprilTag detection) or any robot policy, e.g. elastic.",
    ),
) -> None:
    """Three services on one robot (a classifier, a dense model, a handler) sharing its uplink
    and CPU: joint decisions against independent ones, on an uncontended then a contended
    uplink (see docs/experiments.md)."""
    from experiments import services as sv

    settings = _guard(
        lambda: sv.plan(
            options,
            rounds=rounds,
            fps=fps,
            uncontended_mbit=uncontended_mbit,
            contended_mbit=contended_mbit,
            phase_s=phase_s,
            handler_policy=handler_policy,
        )
    )
    _run(
        options,
        lambda: sv.run(options, settings),
        sv.markdown,
        sv.plot,
        as_json,
        sv.ServicesResult.public,
        tls_key=False,
    )


@bench_app.command("nav")
def nav(
    resolutions: str = typer.Option(
        "320x240,640x480", "--resolutions", help="Camera resolutions WxH, comma-separated."
    ),
    nav_options: str = typer.Option(
        "1,2,3,4,elastic,elastic-segments,off",
        "--options",
        help="Offloading options 1-4, elastic (the runtime's learner over whole suffixes), "
        "elastic-segments (with the split's segments too: option 3 among its actions) and off "
        "(the assistant off, closed loop only), comma-separated.",
    ),
    uplink_mbit: float | None = typer.Option(
        None,
        "--uplink-mbit",
        help="The robot's uplink cap, Mbit/s (default 100: near what 802.11ac WiFi gives one "
        "robot, the paper's link).",
    ),
    laps: int | None = typer.Option(
        None, "--laps", help="Laps of the 7-maneuver circuit (default 10, 1 with --quick)."
    ),
    table5: str = typer.Option(
        "sim",
        "--table5",
        help="Table V in the in-process closed loop (sim) or driven by the robot daemon on the "
        "testbed, one run per maneuver in real time (live).",
    ),
    t_dead: float | None = typer.Option(
        None,
        "--t-dead",
        help="The assistant's T_dead in Table V, seconds: d_coll older than this is not trusted "
        "and the robot brakes to rest (default 1, the assistant's; the paper gives none).",
    ),
    quick: bool = QUICK_OPTION,
    frames: int | None = FRAMES_OPTION,
    robot_cpu: float = ROBOT_CPU_OPTION,
    plots_dir: Path = PLOTS_OPTION,
    no_plots: bool = NO_PLOTS_OPTION,
    workdir: Path | None = WORKDIR_OPTION,
    name: str | None = NAME_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """The navigation assistant paper's Tables III-V (update rate, delays, collisions per
    option and resolution) and Figs. 8-9, on the testbed and in the closed loop."""
    from experiments import nav as nv
    from experiments.nav_rows import (
        DEFAULT_T_DEAD_S,
        check_t_dead,
        parse_options,
        parse_resolutions,
        parse_table5,
    )

    sizes = _guard(lambda: parse_resolutions(resolutions))
    chosen = _guard(lambda: parse_options(nav_options))
    mode = _guard(lambda: parse_table5(table5))
    deadline_s = _guard(lambda: check_t_dead(DEFAULT_T_DEAD_S if t_dead is None else t_dead))
    uplink = nv.DEFAULT_UPLINK_MBIT if uplink_mbit is None else uplink_mbit
    if not (math.isfinite(uplink) and uplink > 0):
        _fail(UserError(f"--uplink-mbit {uplink:g}: must be a positive number"))
    if laps is not None and laps < 1:
        _fail(UserError(f"--laps {laps}: expected at least 1"))
    options = _options(
        quick=quick,
        frames=frames,
        robot_cpu=robot_cpu,
        model=nv.MODEL,
        input_shape=f"3x{sizes[0][1]}x{sizes[0][0]}",
        plots_dir=plots_dir,
        no_plots=no_plots,
        workdir=workdir,
        name=name,
    )
    settings = nv.NavSettings(tuple(sizes), tuple(chosen), uplink, laps, mode, deadline_s)
    _run(
        options,
        lambda: nv.run(options, settings),
        nv.markdown,
        nv.plot,
        as_json,
        nv.public,
        tls_key=False,
    )


@bench_app.command("pool")
def pool(
    sizes: str = typer.Option("1,2,3", "--sizes", help="Pool sizes P, comma-separated."),
    resolution: str = typer.Option("320x240", "--resolution", help="Camera resolution WxH."),
    cloud_cpu: float = typer.Option(
        0.5, "--cloud-cpu", help="Each cloud host's CPU quota, in cores (one thread per host)."
    ),
    fps: float = typer.Option(10.0, "--fps", help="The robot's camera rate (T_f = 1 / fps)."),
    uplink_mbit: float = typer.Option(
        100.0, "--uplink-mbit", help="The robot's uplink cap, Mbit/s (as bench nav's)."
    ),
    no_kill: bool = typer.Option(
        False, "--no-kill", help="Skip the run that kills a pool member beside a standby."
    ),
    quick: bool = QUICK_OPTION,
    frames: int | None = FRAMES_OPTION,
    robot_cpu: float = ROBOT_CPU_OPTION,
    workdir: Path | None = WORKDIR_OPTION,
    name: str | None = NAME_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """The navigation assistant's round-robin scale-out: update frequency with P deployments
    sharing one robot's frames (option 1), and a pool member killed."""
    from experiments import nav_pool as npl
    from experiments.fleet import CLOUD_HOSTS
    from experiments.nav_pool_rows import parse_sizes
    from experiments.nav_rows import parse_resolution

    chosen = _guard(lambda: parse_sizes(sizes, hosts=len(CLOUD_HOSTS), standby=not no_kill))
    size = _guard(lambda: parse_resolution(resolution))
    settings = npl.PoolSettings(tuple(chosen), size, cloud_cpu, fps, uplink_mbit, not no_kill)
    _guard(settings.check)
    options = _options(
        quick=quick,
        frames=frames,
        robot_cpu=robot_cpu,
        model=npl.MODEL,
        input_shape=f"3x{size[1]}x{size[0]}",
        plots_dir=DEFAULT_PLOTS_DIR,
        no_plots=True,
        workdir=workdir,
        name=name,
    )
    _run(
        options,
        lambda: npl.run(options, settings),
        npl.markdown,
        lambda result, out_dir: [],
        as_json,
        _as_is,
        tls_key=False,
    )


@bench_app.command("scale")
def scale(
    robots: str = typer.Option(
        ",".join(map(str, scale_defaults.ROBOTS)), "--robots", help="Robot counts, comma-separated."
    ),
    deployments: str = typer.Option(
        ",".join(map(str, scale_defaults.DEPLOYMENTS)),
        "--deployments",
        help="Deployment counts, comma-separated.",
    ),
    batching: str = typer.Option(
        "both", "--batching", help="on, off, or both side by side (off first)."
    ),
    fps: float = typer.Option(scale_defaults.FPS, "--fps", help="Frames per second per robot."),
    duration_s: float | None = typer.Option(
        None, "--duration-s", help="Measured seconds per cell (default 10, 4 with --quick)."
    ),
    warmup_s: float | None = typer.Option(
        None, "--warmup-s", help="Seconds before measuring (default 2, 1 with --quick)."
    ),
    cut: int = typer.Option(scale_defaults.CUT, "--cut", help="The cut the robots offload at."),
    codec: str = typer.Option(scale_defaults.CODEC, "--codec", help="Codec of the cut's tensors."),
    workers: int = typer.Option(
        scale_defaults.WORKERS, "--workers", help="Workers per deployment."
    ),
    threads: int = typer.Option(
        scale_defaults.THREADS, "--threads", help="onnxruntime threads per session (0: its own)."
    ),
    queue: int = typer.Option(
        scale_defaults.QUEUE, "--queue", help="Waiting slots per deployment beyond its workers."
    ),
    max_queue_delay_ms: float = typer.Option(
        scale_defaults.MAX_QUEUE_DELAY_MS, "--max-queue-delay-ms", help="Batching: longest wait."
    ),
    batch_sizes: str = typer.Option(
        ",".join(map(str, scale_defaults.BATCH_SIZES)),
        "--batch-sizes",
        help="Batching: preferred batch sizes (the largest is the biggest batch).",
    ),
    max_in_flight: int = typer.Option(
        scale_defaults.MAX_IN_FLIGHT_PER_ROBOT,
        "--max-in-flight",
        help="Requests one robot may have admitted at a deployment.",
    ),
    deadline_s: float = typer.Option(
        scale_defaults.DEADLINE_S, "--deadline-s", help="Each frame's deadline, seconds."
    ),
    bound_s: float = typer.Option(
        scale_defaults.BOUND_S, "--bound-s", help="Latency bound (p95), seconds."
    ),
    fairness: bool = typer.Option(
        False,
        "--fairness",
        help="Instead: one robot beside a polite neighbour and beside one sending as fast as it "
        "can, with the --max-in-flight limit and heavy robots at low priority (the defaults), "
        "with the limit alone, and with neither.",
    ),
    arrivals: str = typer.Option(
        "periodic",
        "--arrivals",
        help="How each robot's frames are spaced: periodic (a camera's ticks) or poisson "
        "(exponential gaps, the same mean rate; robots at one rate then collide at random, not "
        "by the phase they started with).",
    ),
    pin_cloud: bool = typer.Option(
        False,
        "--pin-cloud",
        help="Pin the cloud daemons to CPUs of their own (one per worker, all but one CPU at "
        "most) and the registry and load generators to the others (Linux, 2 CPUs or more).",
    ),
    quick: bool = QUICK_OPTION,
    model: str = typer.Option(scale_defaults.MODEL, "--model", help="zoo:NAME or an ONNX file."),
    input_shape: str = typer.Option(
        "x".join(map(str, scale_defaults.INPUT_SHAPE)), "--input-shape", help="Camera image CxHxW."
    ),
    plots_dir: Path = PLOTS_OPTION,
    no_plots: bool = NO_PLOTS_OPTION,
    workdir: Path | None = WORKDIR_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Many robots on this host (loopback, no root): what the cloud serves, with and without
    batching, as robots and deployments are added (emulated robots, real cloud daemons)."""
    from common.zoo import parse_shape
    from experiments import fairness as fair
    from experiments import scale as sc

    err = Console(stderr=True)

    def build() -> Any:
        options = sc.ScaleOptions(
            robots=sc.parse_counts(robots, "--robots"),
            deployments=sc.parse_counts(deployments, "--deployments"),
            batching=sc.parse_batching(batching),
            model=model,
            input_shape=parse_shape(input_shape),
            fps=fps,
            warmup_s=warmup_s
            if warmup_s is not None
            else (scale_defaults.QUICK_WARMUP_S if quick else scale_defaults.WARMUP_S),
            duration_s=duration_s
            if duration_s is not None
            else (scale_defaults.QUICK_DURATION_S if quick else scale_defaults.DURATION_S),
            cut=cut,
            codec=codec,
            deadline_s=deadline_s,
            bound_s=bound_s,
            workers=workers,
            threads=threads,
            queue=queue,
            max_queue_delay_ms=max_queue_delay_ms,
            batch_sizes=sc.parse_counts(batch_sizes, "--batch-sizes"),
            max_in_flight_per_robot=max_in_flight,
            pin_cloud=pin_cloud,
            arrivals=arrivals,
            workdir=workdir,
            log=lambda message: err.print(f"[dim]bench:[/dim] {message}", highlight=False),
        )
        options.check()
        return options

    options = _guard(build)
    try:
        result = fair.run_fairness(options) if fairness else sc.run(options)
    except UserError as exc:
        _fail(exc)
    except KeyboardInterrupt:
        err.print("interrupted; every daemon is gone", highlight=False)
        raise typer.Exit(INTERRUPTED_EXIT_CODE) from None
    if fairness:
        typer.echo(json.dumps(result) if as_json else fair.fairness_markdown(result))
        return
    if not no_plots and result["results"]:
        for path in sc.plot(result, plots_dir):
            err.print(f"plot: {path}", highlight=False)
    typer.echo(json.dumps(result) if as_json else sc.markdown(result))
