"""`elasticfog sim`: replay a trace against one policy, or compare several, offline.

    elasticfog sim --profile vgg.json --policy elastic --trace deploy/traces/glitch-10-3.yaml
    elasticfog sim --model zoo:vgg --trace deploy/traces/cpu-drop.yaml --compare elastic,ans,robot
    elasticfog sim --profile vgg.json --policy elastic --param beta=0.3 --param hedge=false ...

The command parses its options and calls the simulator; bad input (a malformed trace or profile,
an unknown policy, a `--param` the policy does not take or a value it rejects) is one line on
stderr and exit code 2.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from common.errors import UserError

if TYPE_CHECKING:
    from robotd.policies.base import CutTable
    from robotd.sim.simulator import SimResult

DEFAULT_COMPARE_PLOT = Path("sim-compare.png")


def register(app: typer.Typer) -> None:
    """Add `sim` to the root app."""
    app.command("sim", help="Replay a bandwidth/CPU trace against split-decision policies.")(
        sim_command
    )


def sim_command(
    trace: Path = typer.Option(..., "--trace", help="Trace YAML (see deploy/traces/)."),
    model: str | None = typer.Option(
        None, "--model", help="ONNX model path or zoo:NAME, profiled on this host."
    ),
    profile: Path | None = typer.Option(
        None, "--profile", help="Profile JSON, as written by `elasticfog model profile --json`."
    ),
    policy: str | None = typer.Option(
        None,
        "--policy",
        help="elastic, ans, neurosurgeon, robot, cloud[:CODEC], static:K[:CODEC] or oracle.",
    ),
    compare: str | None = typer.Option(
        None, "--compare", help="Comma-separated policies to run on the same trace and seed."
    ),
    param: list[str] | None = typer.Option(
        None,
        "--param",
        metavar="KEY=VALUE",
        help="Override a policy parameter (repeatable), e.g. --param beta=0.3; see "
        "docs/policies.md. With --compare, each policy takes the keys it has.",
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the jitter and entropy draws."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON on stdout."),
    plot: Path | None = typer.Option(
        None,
        "--plot",
        help=f"Write a PNG of latency over time (with --compare: default {DEFAULT_COMPARE_PLOT}).",
    ),
) -> None:
    """Replay a trace against a policy and report latency, regret and settling."""
    try:
        _run(trace, model, profile, policy, compare, param or [], seed, json_out, plot)
    except UserError as exc:
        Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(UserError.exit_code) from None


def _cuts(model: str | None, profile: Path | None, quiet: bool) -> CutTable:
    # Heavy imports (numpy, pydantic, the policies) where the command runs: `elasticfog --help`
    # must stay fast.
    from robotd.policies.base import CutTable
    from robotd.sim.trace import load_profile

    if (model is None) == (profile is None):
        raise UserError("give exactly one of --model MODEL or --profile FILE")
    if profile is not None:
        from robotd.policies.segment_actions import actions_table

        return actions_table(load_profile(profile)[1])  # with the segments it lists, if any
    try:
        from common.profiler import profile_model  # the partitioner; heavy, so imported late
    except ImportError:
        raise UserError(
            "--model needs the profiler (common.profiler); use --profile FILE"
        ) from None
    return CutTable.from_profile(
        profile_model(str(model), progress=not quiet), f"profile of {model}"
    )


def _run(
    trace_path: Path,
    model: str | None,
    profile: Path | None,
    policy: str | None,
    compare: str | None,
    params: list[str],
    seed: int,
    json_out: bool,
    plot: Path | None,
) -> None:
    from robotd.policies import parse_assignments, split_overrides
    from robotd.sim.simulator import Simulator, markdown_table, parse_policy_list, plot_results
    from robotd.sim.trace import load_trace

    if (policy is None) == (compare is None):
        raise UserError("give exactly one of --policy NAME or --compare A,B,...")
    names = [str(policy)] if compare is None else parse_policy_list(compare)
    overrides = parse_assignments(params, "--param")
    params_of = split_overrides(names, overrides, "--param")
    trace, resolved = load_trace(trace_path)
    cuts = _cuts(model, profile, json_out)
    sim = Simulator(cuts, trace, seed=seed, trace_dir=resolved.parent)
    results = [sim.run(name, params_of[name]) for name in names]
    if compare is not None and plot is None:
        plot = DEFAULT_COMPARE_PLOT
    if plot is not None:
        title = f"{trace_path.name}, seed {seed}"
        plot_results(results, plot, title)
    if json_out:
        doc: Any = (
            results[0].summary() if compare is None else {"results": [r.summary() for r in results]}
        )
        typer.echo(json.dumps(doc))
        return
    shown = "".join(f", {key}={value}" for key, value in overrides.items())
    if compare is None:
        typer.echo(_describe(results[0], trace_path, seed, shown))
    else:
        typer.echo(f"{trace_path.name}: {results[0].frames} frames, seed {seed}{shown}\n")
        typer.echo(markdown_table(results))
    if plot is not None:
        typer.echo(f"plot: {plot}")


def _describe(result: SimResult, trace_path: Path, seed: int, shown_params: str) -> str:
    s = result.summary()
    lines = [
        f"{s['policy']} on {trace_path.name}: {s['frames']} frames, seed {seed}{shown_params}",
        f"  mean latency {s['mean_latency_s']:.3f} s, p95 {s['p95_latency_s']:.3f} s; "
        f"oracle {s['oracle_mean_latency_s']:.3f} s (ratio {s['ratio_to_oracle']:.3f})",
        f"  cumulative regret {s['cumulative_regret']:.2f}",
    ]
    for seg, name in zip(s["segments"], result.segment_names, strict=True):
        settle = seg["settle_frames"]
        settled = "never settled" if settle is None else f"settled after {settle} frames"
        label = f" ({name})" if name else ""
        lines.append(
            f"  segment {seg['index']}{label}: mean {seg['mean_latency_s']:.3f} s, "
            f"oracle {seg['oracle_mean_latency_s']:.3f} s, {settled}"
        )
    actions = ", ".join(f"{a} ×{n}" for a, n in s["actions"].items())
    lines.append(f"  actions: {actions}")
    lines.append(f"  decision: median {s['decision_us_median']:.1f} µs")
    return "\n".join(lines)
