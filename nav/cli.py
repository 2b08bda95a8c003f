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
