"""Markdown tables and PNG plots of the experiments (matplotlib without a display)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any


def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: numbers rounded, None as n/a."""
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table; the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(str(h) for h in header) + " |"]
    lines.append("| " + " | ".join([":---", *("---:" for _ in header[1:])]) + " |")
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def save_plot(fig: Any, path: Path) -> Path:
    """Write `fig` as a PNG (creating the folder) and close it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def use_agg() -> None:
    """No display here: render off-screen (before pyplot is imported)."""
    from common.extras import Extra, require

    matplotlib = require("matplotlib", Extra.PLOTS, "the experiment plots")
    matplotlib.use("Agg")
