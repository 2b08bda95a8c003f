"""``elasticfog model ...``: split, check and profile ONNX models; prep them for the camera image;
export the model zoo.

Each command parses its options and calls one function of common.partition, common.profiler,
common.prep or common.zoo, imported inside the command so that other commands do not pay for
onnx imports. ``--json`` prints plain JSON on stdout (the contract other tools read);
otherwise a rich table. Bad input is one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import typer
from rich.console import Console

from common.defaults import DEFAULT_CALIBRATION_FRAMES
from common.errors import UserError

if TYPE_CHECKING:
    from rich.table import Table

F = TypeVar("F", bound=Callable[..., Any])

model_app = typer.Typer(
    name="model",
    help="Split, check and profile ONNX models (a file or zoo:NAME).",
    no_args_is_help=True,
)
zoo_app = typer.Typer(
    help="Models defined in code: seeded, exported to ONNX.", no_args_is_help=True
)
model_app.add_typer(zoo_app, name="zoo")

MODEL_HELP = "ONNX file or zoo:NAME (see `elasticfog model zoo list`)."
# The partitioner names a bad option by its parameter; these commands call it by their flag.
OPTION_FLAGS = {
    "cuts": "--cuts",
    "input_shape": "--input-shape",
    "max_cut_tensors": "--max-cut-tensors",
    "out_dir": "--out",
}
CUTS_HELP = "'auto', or cuts separated by commas; join the tensors of one cut with '+' (a,b+c)."
# Table width when stdout is not a terminal: long tensor names stay on one line in logs.
PIPE_WIDTH = 200
SHAPE_HELP = (
    "zoo:NAME: the image as CxHxW (default 3x240x320; the model's input is uint8 1xHxWxC). "
    "A file: its dynamic dimensions, 3x240x320 (first input) or NAME=1x3x240x320,..."
)


def register(app: typer.Typer) -> None:
    """Add the `model` command group to the root app."""
    app.add_typer(model_app, name="model")


def _user_errors(fn: F) -> F:
    """Print a UserError as one line on stderr and exit 2 (commands never show a traceback)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            Console(stderr=True).print(
                f"[red]error:[/red] {_message(exc)}", highlight=False, soft_wrap=True, markup=True
            )
            raise typer.Exit(exc.exit_code) from None

    return wrapper  # type: ignore[return-value]


def _message(exc: UserError) -> str:
    """The error's message, a partitioner option named by its flag (--input-shape)."""
    from common.partition import OptionError

    if isinstance(exc, OptionError):
        return exc.naming(OPTION_FLAGS.get(exc.option, exc.option))
    return str(exc)


def _print_json(data: Any) -> None:
    typer.echo(json.dumps(data, indent=2))


def _fmt_bytes(n: int) -> str:
    if n >= 1 << 20:
        return f"{n / (1 << 20):.2f} MiB"
    if n >= 1 << 10:
        return f"{n / (1 << 10):.1f} KiB"
    return f"{n} B"


def _fmt_mflops(n: int) -> str:
    return f"{n / 1e6:.1f}"


def _console() -> Console:
    """Stdout console; when stdout is not a terminal (logs, pipes) tables get room not to wrap."""
    return Console(width=None if sys.stdout.isatty() else PIPE_WIDTH)


def _cuts_table(manifest: dict[str, Any], title: str) -> Table:
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    table.add_column("cut", justify="right")
    table.add_column("bytes", justify="right", no_wrap=True)
    table.add_column("robot MFLOP", justify="right")
    table.add_column("cloud MFLOP", justify="right")
    table.add_column("verified")
    table.add_column("max abs err", justify="right", no_wrap=True)
    table.add_column("tensors", overflow="fold")
    for cut in manifest["cuts"]:
        err = cut["max_abs_err"]
        table.add_row(
            str(cut["index"]),
            _fmt_bytes(cut["bytes"]),
            _fmt_mflops(cut["prefix_flops"]),
            _fmt_mflops(cut["suffix_flops"]),
            "yes" if cut["verified"] else "no",
            "-" if err is None else f"{err:.2g}",
            " + ".join(cut["tensors"]),
        )
    return table


def _print_partition(manifest: dict[str, Any], where: str) -> None:
    from common.partition import DOMINATED_PREFIX

    console = _console()
    title = f"{manifest['model']}  sha256 {manifest['digest'][:12]}  ({where})"
    console.print(_cuts_table(manifest, title))
    excluded = manifest.get("excluded", [])
    dominated = [e for e in excluded if e["reason"].startswith(DOMINATED_PREFIX)]
    if dominated:
        console.print(
            f"{len(dominated)} cut(s) left out: another cut sends fewer bytes for the same "
            "robot FLOPs (--all-cuts keeps them)",
            highlight=False,
        )
    for item in excluded:
        if item in dominated:
            continue
        shown = " + ".join(item["tensors"]) or "-"
        console.print(f"excluded {shown}: {item['reason']}", highlight=False, soft_wrap=True)


def _require_cuts(manifest: dict[str, Any], where: str) -> None:
    if not manifest["cuts"]:
        raise UserError(f"no cut of {manifest['model']} passed verification (see {where})")


@model_app.command("split")
@_user_errors
def split_cmd(
    model: str = typer.Argument(..., help=MODEL_HELP),
    out: Path = typer.Option(..., "--out", help="Directory for manifest.json and the sub-models."),
    cuts: str = typer.Option("auto", "--cuts", help=CUTS_HELP),
    max_cut_tensors: int = typer.Option(
        2, "--max-cut-tensors", help="At most this many tensors cross an automatic cut."
    ),
    input_shape: str | None = typer.Option(None, "--input-shape", help=SHAPE_HELP),
    verify: bool = typer.Option(True, "--verify/--no-verify", help="Check prefix∘suffix = full."),
    all_cuts: bool = typer.Option(
        False, "--all-cuts", help="Keep automatic cuts that another cut beats (fewer bytes)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print manifest.json instead of a table."),
) -> None:
    """Cut a model at every candidate point and write prefix/suffix models to --out."""
    from common.partition import parse_cuts, parse_input_shape, split_model

    part = split_model(
        model,
        out,
        cuts=parse_cuts(cuts),
        max_cut_tensors=max_cut_tensors,
        input_shape=parse_input_shape(input_shape),
        verify=verify,
        prune=not all_cuts,
    )
    manifest = part.manifest()
    if as_json:
        _print_json(manifest)
    else:
        _print_partition(manifest, f"{out}/manifest.json")
    _require_cuts(manifest, str(out / "manifest.json"))


@model_app.command("check")
@_user_errors
def check_cmd(
    model: str = typer.Argument(..., help=MODEL_HELP),
    cuts: str = typer.Option("auto", "--cuts", help=CUTS_HELP),
    max_cut_tensors: int = typer.Option(
        2, "--max-cut-tensors", help="At most this many tensors cross an automatic cut."
    ),
    input_shape: str | None = typer.Option(None, "--input-shape", help=SHAPE_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the manifest as JSON."),
) -> None:
    """Check that a model can be split here: list its verified cuts (split kept in the cache)."""
    from common.partition import load_partition, parse_cuts, parse_input_shape

    part = load_partition(
        model,
        parse_cuts(cuts),
        max_cut_tensors,
        parse_input_shape(input_shape),
    )
    manifest = part.manifest()
    if as_json:
        _print_json(manifest)
    else:
        _print_partition(manifest, str(part.dir))
    _require_cuts(manifest, str(part.dir / "manifest.json"))


@model_app.command("profile")
@_user_errors
def profile_cmd(
    model: str = typer.Argument(..., help=MODEL_HELP),
    runs: int = typer.Option(20, "--runs", help="Timed runs per measurement (median reported)."),
    threads: int | None = typer.Option(
        None, "--threads", help="onnxruntime intra-op threads (default: all cores)."
    ),
    cuts: str = typer.Option("auto", "--cuts", help=CUTS_HELP),
    max_cut_tensors: int = typer.Option(
        2, "--max-cut-tensors", help="At most this many tensors cross an automatic cut."
    ),
    input_shape: str | None = typer.Option(None, "--input-shape", help=SHAPE_HELP),
    fresh: bool = typer.Option(False, "--fresh", help="Measure again even if a profile is cached."),
    codecs: bool = typer.Option(
        False,
        "--codecs",
        help="Also measure every (cut, codec) pair on photographs: bytes, encode/decode time, "
        "fidelity to the uncompressed model, and which pairs the bound admits as actions.",
    ),
    fidelity: str | None = typer.Option(
        None,
        "--fidelity",
        help="With --codecs: the bound, as fleet.yaml's fidelity: keys, e.g. "
        "min_top1_agreement=0.99,max_output_rel_err=0.02,lossy_features=true,codecs=jpeg80,"
        "codecs=int8+zstd "
        "(default: top-1 agreement 0.98, lossless only for feature maps).",
    ),
    calibration_frames: int = typer.Option(
        DEFAULT_CALIBRATION_FRAMES, "--calibration-frames", help="With --codecs: photographs used."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the profile as JSON."),
) -> None:
    """Time every cut's prefix and suffix on this host (cached by model digest); with --codecs,
    the (cut, codec) fidelity table."""
    from common.partition import parse_cuts, parse_input_shape
    from common.profiler import profile_model

    if fidelity is not None and not codecs:
        raise UserError("--fidelity needs --codecs")
    bound = _parse_fidelity(fidelity) if codecs else None
    if calibration_frames < 1:
        raise UserError(f"--calibration-frames {calibration_frames}: expected at least 1")
    profile = profile_model(
        model,
        runs=runs,
        threads=threads,
        input_shape=parse_input_shape(input_shape),
        progress=not as_json,
        cuts=parse_cuts(cuts),
        max_cut_tensors=max_cut_tensors,
        refresh=fresh,
    )
    if bound is not None:
        measured = _measure_codecs(
            model,
            parse_input_shape(input_shape),
            parse_cuts(cuts),
            max_cut_tensors,
            threads,
            bound,
            calibration_frames,
            progress=not as_json,
        )
        for cut in profile["cuts"]:
            cut["codecs"] = measured.get(cut["index"], [])
    if as_json:
        _print_json(profile)
        return
    from rich.table import Table

    table = Table(
        title=f"{model}  sha256 {profile['digest'][:12]}  full model {profile['full_ms']:.2f} ms",
        title_justify="left",
    )
    table.add_column("cut", justify="right")
    for name in ("bytes", "robot ms", "cloud ms", "robot MFLOP", "cloud MFLOP"):
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("tensors", overflow="fold")
    for cut in profile["cuts"]:
        table.add_row(
            str(cut["index"]),
            _fmt_bytes(cut["bytes"]),
            f"{cut['prefix_ms']:.2f}",
            f"{cut['suffix_ms']:.2f}",
            _fmt_mflops(cut["prefix_flops"]),
            _fmt_mflops(cut["suffix_flops"]),
            " + ".join(cut["tensors"]),
        )
    _console().print(table)
    if bound is not None:
        _console().print(_codec_table(profile, calibration_frames))


def _parse_fidelity(text: str | None) -> Any:
    """`--fidelity k=v,...` as the profiler's bound; UserError naming a bad key or value.
    Values are read as YAML scalars (as in fleet.yaml); `codecs=NAME` may be repeated."""
    import yaml
    from pydantic import ValidationError

    from common.codec_profile import fidelity_of
    from common.config import FidelityConfig
    from common.yaml_files import format_validation_error

    values: dict[str, Any] = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--fidelity {text!r}: expected key=value pairs separated by commas")
        key = key.strip()
        if key == "codecs":  # names may hold '+' (int8+zstd): repeat the key for a list
            values.setdefault("codecs", []).append(value.strip())
        else:
            values[key] = yaml.safe_load(value)
    try:
        return fidelity_of(FidelityConfig.model_validate(values))
    except ValidationError as exc:
        raise UserError(f"--fidelity: {format_validation_error(exc, FidelityConfig)}") from None


def _measure_codecs(
    model: str,
    input_shape: Any,
    cuts: Any,
    max_cut_tensors: int,
    threads: int | None,
    bound: Any,
    frames: int,
    progress: bool,
) -> dict[int, list[dict[str, Any]]]:
    """Every candidate codec of every cut measured on `frames` still photographs."""
    from rich.progress import Progress

    from common.codec_profile import profile_codecs
    from common.image_input import InputAdapter
    from common.partition import load_partition
    from common.partition.runtime import SplitModel
    from common.photos import still_views

    split = SplitModel(load_partition(model, cuts, max_cut_tensors, input_shape), threads=threads)
    specs = split.input_specs()
    if len(specs) != 1:
        names = ", ".join(s.name for s in specs)
        raise UserError(f"--codecs feeds one camera image; {model} has inputs {names}")
    adapter = InputAdapter(specs[0])
    feeds = [{specs[0].name: adapter(view)} for view in still_views(frames)]
    with Progress(console=Console(stderr=True), transient=True, disable=not progress) as bar:
        task = bar.add_task("measuring codecs", total=split.num_cuts)
        return profile_codecs(split, feeds, bound, advance=lambda: bar.advance(task))


def _codec_table(profile: dict[str, Any], frames: int) -> Table:
    from rich.table import Table

    table = Table(
        title=f"(cut, codec) on {frames} photographs: action = admitted by the fidelity bound",
        title_justify="left",
    )
    columns = ("cut", "codec", "bytes (p10-p90)", "of raw", "enc ms", "dec ms", "top-1", "rel err")
    for name in columns:
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("action", justify="center")
    for cut in profile["cuts"]:
        entries = cut.get("codecs") or []
        raw = next((e["bytes"] for e in entries if e["name"] == "raw"), None)
        for e in entries:
            top1 = e["top1_agreement"]
            table.add_row(
                str(cut["index"]),
                e["name"],
                f"{_fmt_bytes(int(e['bytes']))} ({_fmt_bytes(int(e['bytes_p10']))}-"
                f"{_fmt_bytes(int(e['bytes_p90']))})",
                f"{e['bytes'] / raw:.3f}" if raw else "-",
                f"{e['encode_ms']:.2f}",
                f"{e['decode_ms']:.2f}",
                "-" if top1 is None else f"{top1:.2f}",
                f"{e['rel_err']:.3f}" if e["lossy"] and e["rel_err"] is not None else "-",
                "yes" if e.get("action") else "",
            )
    return table


@model_app.command("prep")
@_user_errors
def prep_cmd(
    model: str = typer.Argument(
        ...,
        help="ONNX file of a float-image model: one input, N×C×H×W (or N×H×W×C, --layout nhwc).",
    ),
    out: Path = typer.Option(..., "--out", help="ONNX file to write."),
    mean: str = typer.Option(
        "0,0,0",
        "--mean",
        help="Per-channel mean, R,G,B, on the [0, 1] image (ImageNet: 0.485,0.456,0.406).",
    ),
    std: str = typer.Option(
        "1,1,1",
        "--std",
        help="Per-channel standard deviation, R,G,B (ImageNet: 0.229,0.224,0.225).",
    ),
    layout: str = typer.Option(
        "nchw", "--layout", help="Layout of the original model's input: nchw or nhwc."
    ),
    rgb: bool = typer.Option(
        True,
        "--rgb/--bgr",
        help="Channel order of the camera image. The robot daemon feeds RGB: keep the default "
        "for a model it runs. --bgr adds a BGR→RGB reorder to the graph (the model is taken to "
        "expect RGB), for a program that feeds OpenCV's BGR frames as they come.",
    ),
    input_shape: str | None = typer.Option(
        None, "--input-shape", help="HxW: fixes a dynamic height and width (e.g. 224x224)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print what was written as JSON."),
) -> None:
    """Wrap a float-image model so that it takes the camera image, uint8 N×H×W×3 (channels
    last): the graph reorders BGR→RGB (--bgr; the model is taken to expect RGB), casts to float,
    scales by 1/255, subtracts --mean, divides by --std and transposes to N×C×H×W (--layout
    nchw). Input and output names stay; the result is checked on a photograph against the
    original model fed the same image normalized by hand, and not written if it differs."""
    from common.prep import (
        ChannelOrder,
        Layout,
        parse_channel_values,
        parse_layout,
        parse_size,
        prep_model,
    )

    result = prep_model(
        model,
        out,
        mean=parse_channel_values(mean, "--mean"),
        std=parse_channel_values(std, "--std"),
        layout=parse_layout(layout),
        camera_order=ChannelOrder.RGB if rgb else ChannelOrder.BGR,
        input_size=None if input_shape is None else parse_size(input_shape),
    )
    if as_json:
        _print_json(result.to_json())
        return
    order = result.camera_order.value.upper()
    reorder = " (reordered to RGB in the graph)" if result.camera_order is ChannelOrder.BGR else ""
    nchw = ", then NCHW" if result.layout is Layout.NCHW else ""
    h, w = result.verify_size
    shape = "×".join(str(d) for d in result.input_shape)
    _console().print(
        f"wrote {out}: input {result.input_name!r} {result.input_dtype} {shape} (N×H×W×3), "
        f"camera image in {order} order{reorder}\n"
        f"front end: cast, /255, mean {_fmt_values(result.mean)}, "
        f"std {_fmt_values(result.std)}{nchw}; outputs {', '.join(result.outputs)}\n"
        f"checked on a {h}×{w} photograph: max abs err {result.max_abs_err:.2g} "
        f"(tolerance {result.tolerance:.2g})",
        highlight=False,
        soft_wrap=True,
    )


def _fmt_values(values: tuple[float, ...]) -> str:
    return ",".join(f"{v:g}" for v in values)


@zoo_app.command("list")
@_user_errors
def zoo_list_cmd(
    as_json: bool = typer.Option(False, "--json", help="Print the list as JSON."),
) -> None:
    """List the zoo models (their weights are seeded, not trained)."""
    from common.zoo import (
        CAMERA_ORDER,
        DEFAULT_INPUT_SHAPE,
        DEFAULT_ZOO_MODEL,
        WEIGHTS_NOTE,
        ZOO_INPUT_DTYPE,
        all_models,
        file_input_shape,
        format_shape,
    )

    # The zoo's own networks, then the graph models other packages register (zoo:stereo).
    rows = [
        {"name": m.name, "description": m.description, "default": m.name == DEFAULT_ZOO_MODEL}
        for m in all_models().values()
    ]
    if as_json:
        _print_json(rows)
        return
    from rich.table import Table

    table = Table(
        title=f"model zoo (default image {format_shape(DEFAULT_INPUT_SHAPE)}: input "
        f"{ZOO_INPUT_DTYPE} {format_shape(file_input_shape(DEFAULT_INPUT_SHAPE))}, "
        f"{CAMERA_ORDER.upper()})",
        caption=WEIGHTS_NOTE,
    )
    table.add_column("name")
    table.add_column("description")
    for row in rows:
        name = f"zoo:{row['name']}" + (" (default)" if row["default"] else "")
        table.add_row(name, str(row["description"]))
    _console().print(table)


@zoo_app.command("export")
@_user_errors
def zoo_export_cmd(
    name: str = typer.Argument(
        ..., help="Zoo model name (vgg, resnet, mobilenet, resnet18, mobilenet_v2)."
    ),
    out: Path = typer.Option(..., "--out", help="ONNX file to write."),
    input_shape: str = typer.Option(
        "3x240x320",
        "--input-shape",
        help="Image size as CxHxW; the file's input is the uint8 camera image 1xHxWxC (RGB).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print what was written as JSON."),
) -> None:
    """Export a zoo model to an ONNX file (seeded weights: the same file every time). Its input is
    the uint8 camera image, 1×H×W×C in RGB order, normalized in the graph."""
    from common import zoo
    from common.models import file_digest, zoo_shape

    name = name.removeprefix("zoo:")
    zoo.get(name)  # unknown names fail before the graph builder is imported
    shape = zoo_shape(zoo.parse_shape(input_shape))
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as {name}.onnx")
    zoo.export(name, out, shape)
    file_shape = zoo.file_input_shape(shape)
    info = {
        "name": name,
        "path": str(out),
        "digest": file_digest(out),
        "input_shape": list(file_shape),
        "input_dtype": zoo.ZOO_INPUT_DTYPE,
        "camera_order": zoo.CAMERA_ORDER,
    }
    if as_json:
        _print_json(info)
    else:
        _console().print(
            f"wrote {out} (zoo:{name}, input {zoo.ZOO_INPUT_DTYPE} "
            f"{zoo.format_shape(file_shape)} in {zoo.CAMERA_ORDER.upper()} order, "
            f"sha256 {info['digest'][:12]})",
            highlight=False,
        )
