"""Settings every experiment shares, and the one place that opens a testbed fleet for it.

What stands for what (see docs/experiments.md): the robot is the `robot` host with a cgroup CPU
quota of `robot_cpu` of one core (0.5 by default: MobileNetV2 at 320x240 then takes about 60 ms
there, the pace of a small robot computer's CPU such as a Raspberry Pi 4 class board, about as
long as its JPEG frame takes to cross 1 Mbit/s and be classified in the cloud), the uplink is the
`tc` cap on the robot's link, the deployments are cloud daemons on hosts of their own with the
rest of the machine, and a frame is a photograph with camera motion (`photo` source) as uint8.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from common.defaults import DEFAULT_CAMERA_SOURCE, ZOO_PREFIX
from common.errors import UserError
from common.path_options import model_path, option_dir

from .defaults import DEFAULT_INPUT_SHAPE, DEFAULT_MODEL, DEFAULT_ROBOT_CPU
from .fleet import POLICY_VARIANTS
from .runner import DEFAULT_HOSTS, TestbedFleet

DOCS_IMG_DIR = Path(__file__).resolve().parents[2] / "docs" / "img"


@dataclass
class BenchOptions:
    """Options of every `elasticfog bench` command."""

    model: str = DEFAULT_MODEL
    """zoo:NAME or an ONNX file; `check()` makes a file's path absolute (relative: to the
    working directory)."""
    input_shape: tuple[int, ...] = ()
    """(): the default, set by `check()`: a file's own input shape when its dimensions are fixed,
    else (a zoo model, dynamic dimensions) DEFAULT_INPUT_SHAPE."""
    robot_cpu: float = DEFAULT_ROBOT_CPU
    source: str = DEFAULT_CAMERA_SOURCE
    """The robot's camera (`--source` of the single-edge experiments): a `photo` or `synthetic`
    spec, generated on the robot (e.g. `photo:astronaut,motion=pan`)."""
    frames: int | None = None
    """Frames per robot run; None: the experiment's default (smaller with `quick`)."""
    quick: bool = False
    workdir: Path | None = None
    """Where fleets, telemetry and logs go; None: a temporary folder removed after a clean run."""
    plots_dir: Path | None = DOCS_IMG_DIR
    """Where PNG plots go; None: no plots."""
    name: str | None = None
    """Testbed name (prefix of its namespaces); None: one of its own."""
    tls: bool = False
    """Mutual TLS and access control on every link (`--tls`)."""
    log: Callable[[str], None] = lambda message: None

    def check(self) -> None:
        """Check the options and resolve the paths and the shape, before anything starts: a
        relative path is the working directory's (the fleet files are written elsewhere)."""
        if not (math.isfinite(self.robot_cpu) and 0.01 <= self.robot_cpu <= 16):
            raise UserError(f"--robot-cpu {self.robot_cpu:g}: expected 0.01 to 16 (cores)")
        if self.frames is not None and self.frames < 1:
            raise UserError(f"--frames {self.frames}: expected at least 1")
        check_source(self.source)
        self.model = model_path(self.model)
        if not self.input_shape:
            self.input_shape = default_input_shape(self.model)
        if self.workdir is not None:
            self.workdir = option_dir(self.workdir, "--workdir")
        if self.plots_dir is not None:
            self.plots_dir = option_dir(self.plots_dir, "--plots-dir")

    def frames_or(self, full: int, quick: int) -> int:
        """The frames of one run: --frames if given, else the experiment's default."""
        if self.frames is not None:
            return self.frames
        return quick if self.quick else full


def default_input_shape(model: str) -> tuple[int, ...]:
    """The shape a bench gives `model` when --input-shape is not given: an ONNX file's own when
    every dimension of its first input is fixed (besides a dynamic batch), else
    DEFAULT_INPUT_SHAPE (a zoo model; dynamic dimensions)."""
    if model.startswith(ZOO_PREFIX):
        return DEFAULT_INPUT_SHAPE
    # Imported here: onnx is only needed for a file.
    from common.partition.errors import OptionError
    from common.partition.loading import load_onnx, resolve_input_shapes

    graph = load_onnx(Path(model)).graph
    initializers = {t.name for t in graph.initializer}
    inputs = [vi for vi in graph.input if vi.name not in initializers]
    try:
        shapes = resolve_input_shapes(inputs[:1], None)
    except OptionError:  # a dynamic dimension besides the batch: the default fills it
        return DEFAULT_INPUT_SHAPE
    return next(iter(shapes.values()), DEFAULT_INPUT_SHAPE)


def check_source(source: str) -> None:
    """A bench robot's source must be one it makes itself (`photo` or `synthetic`): a file's
    relative path would be the fleet file's, and nothing publishes frames to a bench robot."""
    from common.source_spec import PhotoSpec, SourceError, SyntheticSpec, parse_source

    try:
        spec = parse_source(source)
    except SourceError as exc:
        raise UserError(f"--source: {exc}") from None
    if not isinstance(spec, PhotoSpec | SyntheticSpec):
        raise UserError(
            f"--source {source!r}: the bench's robot takes a photo[...] or synthetic[...] source"
        )


def parse_floats(text: str, what: str) -> list[float]:
    """'0.5,1,2' -> [0.5, 1.0, 2.0]; a UserError naming `what` for anything else."""
    values: list[float] = []
    for part in text.split(","):
        part = part.strip()
        try:
            value = float(part)
        except ValueError:
            raise UserError(f"{what}: {part!r} is not a number (expected e.g. 0.5,1,2)") from None
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"{what}: {part!r} must be a positive number")
        values.append(value)
    if not values:
        raise UserError(f"{what}: expected at least one value")
    return values


def parse_names(text: str, what: str, allowed: Sequence[str] | None = None) -> list[str]:
    """'elastic,cloud' -> ['elastic', 'cloud'], checked against `allowed` if given."""
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise UserError(f"{what}: expected at least one name")
    if allowed is not None:
        known = [*allowed, *POLICY_VARIANTS]
        # Codec baselines and static cuts take any cut and codec; the robot checks them against
        # its profile when it starts.
        parametric = ("static:", "cloud:")
        bad = [n for n in names if n not in known and not n.startswith(parametric)]
        if bad:
            raise UserError(
                f"{what}: unknown {', '.join(bad)}; expected some of {', '.join(known)}"
            )
    return names


@contextlib.contextmanager
def open_fleet(options: BenchOptions, hosts: Sequence[str] | None = None) -> Iterator[TestbedFleet]:
    """A testbed fleet in `options.workdir` (or a temporary folder), always torn down.

    A temporary folder is removed after a clean run and kept (and named) after a failure."""
    with (
        bench_workdir(options.workdir, "elasticfog-bench-", options.log) as workdir,
        TestbedFleet(
            workdir,
            name=options.name,
            hosts=hosts or DEFAULT_HOSTS,
            log=options.log,
            tls=options.tls,
        ) as tf,
    ):
        yield tf


@contextlib.contextmanager
def bench_workdir(workdir: Path | None, prefix: str, log: Callable[[str], None]) -> Iterator[Path]:
    """`workdir`, or a temporary folder (named by `prefix`) that is removed after a clean run
    and kept, its path logged, after a failure (its daemon logs say why)."""
    if workdir is not None:
        yield workdir
        return
    own = Path(tempfile.mkdtemp(prefix=prefix))
    ok = False
    try:
        yield own
        ok = True
    finally:
        if ok:
            shutil.rmtree(own, ignore_errors=True)
        else:
            log(f"logs kept in {own}")
