"""The registry at scale, by simulation: N robots and M deployments in simulated time, no Zenoh.

The simulated fleet (`registry_sim_fleet.py` beside this file) drives the registry daemon's own
control loop, scheduler, switch protocol and sqlite RIB with churn and latency reports at 10 Hz
per robot. Measured after `--warmup-s` of simulated time, over `--duration-s` (wall clock):
- one scheduling round (`ControlLoop.schedule_all`: every live robot evaluated, moves carried
  out): median and p95; decisions per second = robots evaluated per second of round time;
- moves (route changes published) and RIB write transactions per simulated second (each public
  write method of `Rib` is one transaction); profile windows saved per simulated second;
- the cost of feeding the measurements (µs per telemetry or probe report, decoding not included),
  the worst profile save, full garbage collections and the longest collector pause, and the
  registry's share of one core (all its work per simulated second: the registry is one Python
  process, so this must stay well below 1);
- memory: peak RSS of the process (each size runs in a fresh one) and its growth from the start.

    python benchmarks/registry_sim.py [--robots 10,30,100,300,1000] [--deployments 100]
        [--fixed-deployments] [--warmup-s 20] [--duration-s 20] [--seed 0] [--churn 1]
        [--baseline-src DIR] [--json] [--plot FILE.png]

With fewer robots than `--deployments`, a size runs with as many deployments as robots (10 robots
on 100 deployments is not a fleet anyone runs), unless `--fixed-deployments`. `--baseline-src DIR`
runs each size a second time, just before, with `DIR` (a copy of `registry/` and `common/` of
another revision: `git archive REV registry common | tar -x -C DIR`) first on the import path:
both sets of figures are measured side by side, in one run. See docs/scale.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from registry_sim_fleet import (
    DEFAULT_DURATION_S,
    DEFAULT_TELEMETRY_HZ,
    DEFAULT_WARMUP_S,
    SimConfig,
    SizeResult,
    simulate,
)

from robotd.frame_path.probes import PROBE_INTERVAL_S

DEFAULT_ROBOTS = (10, 30, 100, 300, 1000)
DEFAULT_DEPLOYMENTS = 100
# The target for one round at 1,000 robots and 100 deployments.
TARGET_ROUND_MS = 50.0


# -- several sizes, each in a fresh process -------------------------------------------------------
def _run_child(cfg: SimConfig, src: str | None) -> SizeResult:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
    done = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(asdict(cfg))],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        where = f" with {src} first on the path" if src else ""
        raise SystemExit(
            f"the simulation of {cfg.robots} robots{where} failed:\n{done.stderr[-3000:]}"
        )
    return SizeResult(**json.loads(done.stdout.strip().splitlines()[-1]))


def run_sizes(
    sizes: Sequence[int],
    deployments: int,
    *,
    fixed: bool,
    baseline_src: str | None,
    base: dict[str, Any],
    progress: Callable[[str], None],
) -> dict[str, list[SizeResult]]:
    """Every size, each in a fresh process (the baseline's just before it, when asked)."""
    out: dict[str, list[SizeResult]] = {"results": [], "baseline": []}
    for robots in sizes:
        cfg = SimConfig(
            robots=robots, deployments=deployments if fixed else min(deployments, robots), **base
        )
        if baseline_src is not None:
            progress(f"{robots} robots, {cfg.deployments} deployments: baseline")
            out["baseline"].append(_run_child(cfg, baseline_src))
        progress(f"{robots} robots, {cfg.deployments} deployments")
        out["results"].append(_run_child(cfg, None))
    return out


# -- output ----------------------------------------------------------------------------------------
_COLUMNS = (
    ("robots", "robots", "{:d}"),
    ("deployments", "deps", "{:d}"),
    ("round_median_ms", "round p50 ms", "{:.2f}"),
    ("round_p95_ms", "round p95 ms", "{:.2f}"),
    ("decisions_per_s", "decisions/s", "{:,.0f}"),
    ("moves_per_s", "moves/s", "{:.2f}"),
    ("rib_writes_per_s", "RIB tx/s", "{:.1f}"),
    ("profiles_saved_per_s", "profiles saved/s", "{:,.0f}"),
    ("reports_per_s", "reports/s", "{:,.0f}"),
    ("ingest_us_per_report", "ingest µs", "{:.1f}"),
    ("save_max_ms", "save max ms", "{:.1f}"),
    ("gc_full_collections", "full GCs", "{:d}"),
    ("gc_max_pause_ms", "GC max ms", "{:.0f}"),
    ("core_share", "core share", "{:.2f}"),
    ("peak_rss_mib", "peak RSS MiB", "{:.0f}"),
)


def format_table(results: Sequence[SizeResult], title: str) -> str:
    """A plain-text table of the figures."""
    rows = [[fmt.format(getattr(r, name)) for name, _, fmt in _COLUMNS] for r in results]
    heads = [head for _, head, _ in _COLUMNS]
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(heads)]
    lines = [title, "  ".join(h.rjust(w) for h, w in zip(heads, widths, strict=True))]
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)


def growth_exponent(results: Sequence[SizeResult]) -> float:
    """The slope of log(round median) against log(robots) from the smallest size to the largest
    (1: linear in robots)."""
    first, last = results[0], results[-1]
    return math.log(last.round_median_ms / first.round_median_ms) / math.log(
        last.robots / first.robots
    )


def plot(out: dict[str, list[SizeResult]], path: Path, deployments: str) -> None:
    """Round time against robots, log-log, with a linear-growth guide and the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    now = "after" if out["baseline"] else "this revision"
    series = [(now, out["results"], "C0"), ("before", out["baseline"], "C3")]
    for label, results, color in series:
        if not results:
            continue
        robots = [r.robots for r in results]
        ax.plot(
            robots,
            [r.round_median_ms for r in results],
            "o-",
            color=color,
            label=f"{label}: median",
        )
        ax.plot(
            robots,
            [r.round_p95_ms for r in results],
            "^--",
            color=color,
            alpha=0.6,
            label=f"{label}: p95",
        )
    first = out["results"][0]
    xs = [r.robots for r in out["results"]]
    ax.plot(
        xs,
        [first.round_median_ms * x / first.robots for x in xs],
        ":",
        color="grey",
        label="linear in robots",
    )
    ax.axhline(TARGET_ROUND_MS, color="grey", lw=0.8)
    ax.text(xs[0], TARGET_ROUND_MS * 1.1, f"{TARGET_ROUND_MS:g} ms", color="grey", fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"robots (deployments: {deployments})")
    ax.set_ylabel("one scheduling round, ms")
    ax.set_title("Registry scheduling round (simulated fleet, one core)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _sizes(text: str) -> list[int]:
    try:
        sizes = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected robot counts like 10,100,1000, got {text!r}"
        ) from None
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"robot counts must be >= 1, got {text!r}")
    return sorted(sizes)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--robots", type=_sizes, default=list(DEFAULT_ROBOTS))
    parser.add_argument("--deployments", type=int, default=DEFAULT_DEPLOYMENTS)
    parser.add_argument(
        "--fixed-deployments",
        action="store_true",
        help="the same number of deployments at every size",
    )
    parser.add_argument("--warmup-s", type=float, default=DEFAULT_WARMUP_S)
    parser.add_argument("--duration-s", type=float, default=DEFAULT_DURATION_S)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--churn", type=float, default=1.0, help="churn rate scale (0: none)")
    parser.add_argument("--telemetry-hz", type=float, default=DEFAULT_TELEMETRY_HZ)
    parser.add_argument("--probe-interval-s", type=float, default=PROBE_INTERVAL_S)
    parser.add_argument(
        "--baseline-src",
        metavar="DIR",
        help="also run each size with DIR (registry/, common/) first on the path",
    )
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--plot", type=Path, metavar="FILE.png", help="round time vs robots")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(asdict(simulate(SimConfig(**json.loads(args.child))))))
        return 0
    if args.baseline_src is not None and not (Path(args.baseline_src) / "registry").is_dir():
        parser.error(f"--baseline-src {args.baseline_src}: no registry/ folder there")
    base = {
        "warmup_s": args.warmup_s,
        "duration_s": args.duration_s,
        "seed": args.seed,
        "churn": args.churn,
        "telemetry_hz": args.telemetry_hz,
        "probe_interval_s": args.probe_interval_s,
    }
    try:
        SimConfig(robots=1, deployments=1, **base)
    except ValueError as exc:
        parser.error(str(exc))
    out = run_sizes(
        args.robots,
        args.deployments,
        fixed=args.fixed_deployments,
        baseline_src=args.baseline_src,
        base=base,
        progress=lambda line: print(line, file=sys.stderr, flush=True),
    )
    if args.plot is not None:
        deps = (
            str(args.deployments) if args.fixed_deployments else f"min(robots, {args.deployments})"
        )
        plot(out, args.plot, deps)
    if args.json:
        print(
            json.dumps(
                {
                    "params": {
                        **base,
                        "deployments": args.deployments,
                        "fixed_deployments": args.fixed_deployments,
                        "baseline_src": args.baseline_src,
                    },
                    **{k: [asdict(r) for r in v] for k, v in out.items()},
                },
                indent=2,
            )
        )
        return 0
    if out["baseline"]:
        print(format_table(out["baseline"], f"before ({args.baseline_src})"))
        print()
    print(format_table(out["results"], "after" if out["baseline"] else "this revision"))
    for before, after in zip(
        out["baseline"] or [], out["results"] if out["baseline"] else [], strict=True
    ):
        speedup = before.round_median_ms / after.round_median_ms
        alike = before.route_changes_digest == after.route_changes_digest
        print(
            f"{after.robots} robots: round median {before.round_median_ms:.1f} ms ->"
            f" {after.round_median_ms:.1f} ms ({speedup:.0f}x);"
            f" {'the same' if alike else 'DIFFERENT'} route changes"
        )
    for label, results in (("before", out["baseline"]), ("now", out["results"])):
        for r in results:
            reasons = ", ".join(f"{k} {v:.2f}" for k, v in r.moves_by_reason.items()) or "none"
            print(f"{label}, {r.robots} robots: moves/s by reason: {reasons}")
        if len(results) > 1:
            print(
                f"{label}: round time grows as robots^{growth_exponent(results):.2f}"
                " from the smallest size to the largest (1: linear)"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
