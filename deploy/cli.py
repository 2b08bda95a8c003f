"""`elasticfog testbed ...`: build, shape and tear down the network-namespace testbed (root).

Each command parses its options and calls one method of `deploy.testbed.Testbed`; the testbed's
state file lets `shape`, `cpu`, `exec`, `status` and `down` find what `up` built in another process.
The testbed name defaults to `ef` (or $ELASTICFOG_TESTBED).
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from common.errors import UserError

if TYPE_CHECKING:
    pass
from deploy.testbed_defaults import DEFAULT_HOSTS, DEFAULT_NAME, DEFAULT_SUBNET, NAME_ENV

testbed_app = typer.Typer(
    name="testbed",
    help="Multi-host testbed on this machine: network namespaces, tc shaping, CPU quotas (root).",
    no_args_is_help=True,
)

# After Ctrl-C an `exec`ed command gets this long to exit before it is killed.
EXEC_INTERRUPT_GRACE_S = 5.0

NAME_OPTION = typer.Option(
    DEFAULT_NAME, "--name", "-n", envvar=NAME_ENV, help="Testbed name (prefixes its namespaces)."
)
JSON_OPTION = typer.Option(False, "--json", help="Print plain JSON on stdout.")


def register(app: typer.Typer) -> None:
    """Add the `testbed` command group to the root app."""
    app.add_typer(testbed_app, name="testbed")


@contextmanager
def _user_errors() -> Iterator[None]:
    # Bad input is one line on stderr and exit code 2, never a traceback.
    try:
        yield
    except UserError as exc:
        Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(exc.exit_code) from None


def _mbit(value: float | None) -> str:
    return "unlimited" if value is None else f"{value:g} Mbit/s"


def _fraction(value: float | None) -> str:
    return "unlimited" if value is None else f"{value:g} core"


@testbed_app.command("up")
def up(
    name: str = NAME_OPTION,
    hosts: str = typer.Option(
        ",".join(DEFAULT_HOSTS), "--hosts", help="Comma-separated host names, one namespace each."
    ),
    subnet: str = typer.Option(
        DEFAULT_SUBNET, "--subnet", help="Private IPv4 range, used only inside the testbed."
    ),
    as_json: bool = JSON_OPTION,
) -> None:
    """Create one network namespace per host, joined by a bridge; print host → address."""
    # deploy.testbed (psutil, tc shaping, cgroups) where a command runs: `elasticfog --help` must
    # stay fast.
    from deploy.testbed import Testbed

    with _user_errors():
        testbed = Testbed(
            name, hosts=[h.strip() for h in hosts.split(",") if h.strip()], subnet=subnet
        )
        addresses = testbed.up()
    if as_json:
        typer.echo(json.dumps({"name": name, "subnet": subnet, "hosts": addresses}))
        return
    from rich.table import Table

    table = Table(title=f"testbed {name} is up ({subnet})")
    for column in ("host", "address", "namespace"):
        table.add_column(column)
    for host, address in addresses.items():
        table.add_row(host, address, testbed.netns(host))
    console = Console()
    console.print(table)
    first = next(iter(addresses))
    console.print(
        f"run on a host: elasticfog testbed exec {first} -- CMD   "
        f"(hosts resolve each other by name); remove: elasticfog testbed down --name {name}",
        highlight=False,
    )


@testbed_app.command("down")
def down(name: str = NAME_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Remove the testbed: processes, namespaces, cgroups (also what a crashed run left)."""
    from deploy.testbed import Testbed

    with _user_errors():
        removed = Testbed(name).down()
    if as_json:
        typer.echo(json.dumps({"name": name, "removed": removed}))
    elif removed:
        kinds = [item.split(" ", 1)[0] for item in removed]
        counts = ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds)))
        typer.echo(f"testbed {name} removed ({counts})")
    else:
        typer.echo(f"testbed {name}: nothing to remove")


@testbed_app.command("shape")
def shape(
    host: str = typer.Argument(..., help="Host whose link to cap."),
    uplink_mbit: float | None = typer.Option(
        None, "--uplink-mbit", help="Cap on what the host sends (omitted: unlimited)."
    ),
    downlink_mbit: float | None = typer.Option(
        None, "--downlink-mbit", help="Cap on what the host receives (omitted: unlimited)."
    ),
    name: str = NAME_OPTION,
) -> None:
    """Cap a host's link with tc (htb); run again to change it while traffic flows."""
    from deploy.testbed import Testbed

    with _user_errors():
        testbed = Testbed.attach(name)
        testbed.shape(host, uplink_mbit, downlink_mbit)
        rates = testbed.link_rates(host)
    typer.echo(
        f"{host}: uplink {_mbit(rates['uplink_mbit'])}, downlink {_mbit(rates['downlink_mbit'])}"
    )


@testbed_app.command("cpu")
def cpu(
    host: str = typer.Argument(..., help="Host whose processes to cap."),
    fraction: float | None = typer.Option(
        None, "--fraction", help="CPU cap in cores for all the host's processes, e.g. 0.5."
    ),
    unlimited: bool = typer.Option(False, "--unlimited", help="Remove the cap."),
    name: str = NAME_OPTION,
) -> None:
    """Cap the CPU of everything started on a host (cgroup-v1 CFS quota); changeable at run time."""
    from deploy.testbed import Testbed

    with _user_errors():
        if (fraction is None) == (not unlimited):
            raise UserError("give either --fraction F (cores, e.g. 0.5) or --unlimited")
        testbed = Testbed.attach(name)
        testbed.cpu(host, None if unlimited else fraction)
        now = testbed.cpu_fraction(host)
    typer.echo(f"{host}: cpu {_fraction(now)}")


@testbed_app.command("exec")
def exec_(
    host: str = typer.Argument(..., help="Host to run on."),
    command: list[str] = typer.Argument(..., help="The command, after `--`."),
    name: str = NAME_OPTION,
) -> None:
    """Run a command on a host (its namespace and CPU cgroup); exits with the command's code."""
    from deploy.testbed import Testbed

    with _user_errors():
        testbed = Testbed.attach(name)
        # Same process group as this CLI: Ctrl-C at the terminal reaches the command as well.
        proc = testbed.popen(host, command, start_new_session=False)
    try:
        code = proc.wait()
    except KeyboardInterrupt:
        try:
            code = proc.wait(timeout=EXEC_INTERRUPT_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
    # Killed by signal N: the shell's convention, 128 + N.
    raise typer.Exit(128 - code if code < 0 else code)


@testbed_app.command("status")
def status(name: str = NAME_OPTION, as_json: bool = JSON_OPTION) -> None:
    """Show hosts, addresses, link caps, CPU caps, processes and byte counters."""
    from deploy.testbed import Testbed

    with _user_errors():
        info: dict[str, Any] = Testbed.attach(name).status()
    if as_json:
        typer.echo(json.dumps(info))
        return
    from rich.table import Table

    table = Table(title=f"testbed {info['name']} ({info['subnet']})")
    for column in ("host", "address", "uplink", "downlink", "cpu", "processes", "tx", "rx"):
        table.add_column(column)
    for host, entry in info["hosts"].items():
        table.add_row(
            host,
            entry["address"],
            _mbit(entry.get("uplink_mbit")),
            _mbit(entry.get("downlink_mbit")),
            _fraction(entry.get("cpu_fraction")),
            str(len(entry.get("pids", []))),
            f"{entry.get('tx_bytes', 0):,} B",
            f"{entry.get('rx_bytes', 0):,} B",
        )
    Console().print(table)
