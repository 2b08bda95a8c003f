"""Start-up time of the `elasticfog` CLI, side by side with `python -c "import typer"`.

Each case is a whole process, timed from spawn to exit (wall clock, `time.perf_counter`):
`elasticfog --help`, `elasticfog routes --help`, `elasticfog model --help`, and the floor any
typer CLI pays: an interpreter that imports typer and exits. The cases run interleaved (one round
runs each once, in a fresh order per round), so a neighbour's load on a shared host falls on all
of them alike; the table gives the median and p90 per case and the ratio of `--help` to the floor.
The CLI runs through its console script next to this interpreter (the venv's `bin/elasticfog`),
as a user types it; without one, through `python -c` calling `common.cli.main`. The children
inherit the environment: with PYTHONDONTWRITEBYTECODE set, no .pyc is written and every start
compiles the project's modules again (the report says which).

    python benchmarks/cli_startup.py [--runs 21] [--warmup 2] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

DEFAULT_RUNS = 21
DEFAULT_WARMUP = 2
FLOOR = "import typer"
HELP = "elasticfog --help"
P90 = 0.9


def _cli() -> list[str]:
    script = Path(sys.executable).with_name("elasticfog")
    if script.is_file():
        return [str(script)]
    found = shutil.which("elasticfog")
    if found is not None:
        return [found]
    return [sys.executable, "-c", "import sys; from common.cli import main; sys.exit(main())"]


def cases() -> dict[str, list[str]]:
    """Case name → argv."""
    cli = _cli()
    return {
        HELP: [*cli, "--help"],
        "elasticfog routes --help": [*cli, "routes", "--help"],
        "elasticfog model --help": [*cli, "model", "--help"],
        FLOOR: [sys.executable, "-c", "import typer"],
    }


def time_once(argv: list[str]) -> float:
    """Seconds from spawn to exit of one process; RuntimeError when it fails."""
    env = {**os.environ, "COLUMNS": "100"}
    t0 = time.perf_counter()
    done = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    elapsed = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: exit {done.returncode}: {done.stderr.decode()}")
    return elapsed


def p90(samples: list[float]) -> float:
    """The 90th percentile (nearest rank)."""
    ranked = sorted(samples)
    return ranked[min(len(ranked) - 1, max(0, round(P90 * len(ranked)) - 1))]


def measure(runs: int, warmup: int, seed: int) -> dict[str, list[float]]:
    """Seconds per case, `runs` rounds after `warmup` untimed ones, cases shuffled per round."""
    argvs = cases()
    names = list(argvs)
    rng = random.Random(seed)
    samples: dict[str, list[float]] = {name: [] for name in names}
    for round_index in range(warmup + runs):
        rng.shuffle(names)
        for name in names:
            elapsed = time_once(argvs[name])
            if round_index >= warmup:
                samples[name].append(elapsed)
    return samples


def bytecode() -> str:
    """Whether the children read cached bytecode of the project's modules."""
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        return "not written (PYTHONDONTWRITEBYTECODE): each start compiles the project's modules"
    prefix = os.environ.get("PYTHONPYCACHEPREFIX")
    return f"cached under {prefix}" if prefix else "cached (__pycache__)"


def report(samples: dict[str, list[float]]) -> dict[str, Any]:
    """Medians and p90s in ms, and `--help` over the floor."""
    rows = {
        name: {
            "median_ms": statistics.median(values) * 1000,
            "p90_ms": p90(values) * 1000,
            "runs": len(values),
        }
        for name, values in samples.items()
    }
    ratio = rows[HELP]["median_ms"] / rows[FLOOR]["median_ms"]
    return {
        "python": sys.version.split()[0],
        "cpus": os.cpu_count(),
        "bytecode": bytecode(),
        "cases": rows,
        "help_over_import_typer": ratio,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=DEFAULT_RUNS, help="timed rounds")
    parser.add_argument("--warmup", type=int, default=DEFAULT_WARMUP, help="untimed rounds first")
    parser.add_argument("--seed", type=int, default=0, help="seed of the per-round order")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    doc = report(measure(args.runs, args.warmup, args.seed))
    if args.json:
        print(json.dumps(doc, indent=2))
        return
    runs = next(iter(doc["cases"].values()))["runs"]
    print(f"{runs} runs per case, interleaved; Python {doc['python']}, {doc['cpus']} CPUs")
    print(f"bytecode: {doc['bytecode']}\n")
    print("| command | median | p90 |")
    print("|---|---|---|")
    for name, row in doc["cases"].items():
        shown = f'python -c "{name}"' if name == FLOOR else name
        print(f"| `{shown}` | {row['median_ms']:.0f} ms | {row['p90_ms']:.0f} ms |")
    print(f"\n`{HELP}` / `import typer`: {doc['help_over_import_typer']:.2f}×")


if __name__ == "__main__":
    main()
