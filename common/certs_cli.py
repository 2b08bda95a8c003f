"""`elasticfog certs init|add|show`: the fleet's CA and host certificates (common/certs.py).

    elasticfog certs init DIR --hosts registry,edge-1,edge-2,robot-1 [--ip HOST=ADDR ...]
                              [--dns HOST=NAME ...] [--days N] [--force]
    elasticfog certs add HOST [--dir DIR] [--ip [HOST=]ADDR ...] [--dns [HOST=]NAME ...] [--days N]
    elasticfog certs show [--dir DIR] [--json]

`init` also makes the read-only `cli` certificate. Files: DIR/ca.crt, DIR/ca.key, DIR/<host>.crt,
DIR/<host>.key (keys 0600). Each command parses its options and calls one function of
common.certs, imported where it runs (`cryptography` is not loaded for `elasticfog --help`).
Bad input is one line on stderr and exit code 2.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from common.errors import UserError

DEFAULT_DIR = "certs"  # a str: typer would run a Path default through pydantic
DEFAULT_DAYS = 365  # common.certs.DEFAULT_DAYS, kept here so `--help` needs no cryptography

# An unset `--help` flag is coerced through pydantic by typer (see common.cli.ROOT_DEFAULTS):
# False from the default map keeps `elasticfog certs CMD --help` light.
_HELP_UNSET = {"help": False}
certs_app = typer.Typer(
    name="certs",
    help="The fleet's TLS certificates: a fleet CA and one certificate per host.",
    no_args_is_help=True,
    context_settings={
        "default_map": {**_HELP_UNSET, **{c: dict(_HELP_UNSET) for c in ("init", "add", "show")}}
    },
)

IP_OPTION = typer.Option(
    None, "--ip", help="Extra IP SAN, HOST=ADDR (repeat; 127.0.0.1 is always there)."
)
DNS_OPTION = typer.Option(
    None, "--dns", help="Extra DNS SAN, HOST=NAME (repeat; localhost is always there)."
)
DAYS_OPTION = typer.Option(DEFAULT_DAYS, "--days", min=1, help="Validity in days.")
DIR_OPTION = typer.Option(DEFAULT_DIR, "--dir", help="The certificate folder (has ca.crt).")


def register(app: typer.Typer) -> None:
    """Add the `certs` command group to the root app."""
    app.add_typer(certs_app, name="certs")


def _fail(exc: UserError) -> typer.Exit:
    typer.echo(f"error: {exc}", err=True)
    return typer.Exit(exc.exit_code)


def _hosts(text: str) -> list[str]:
    hosts = [h.strip() for h in text.split(",") if h.strip()]
    if not hosts:
        raise UserError("--hosts: give at least one host, e.g. registry,edge-1,robot-1")
    return hosts


def _for_host(values: list[str], host: str) -> list[str]:
    """`certs add HOST --ip ADDR` means HOST=ADDR."""
    return [v if "=" in v else f"{host}={v}" for v in values]


@certs_app.command("init")
def init(
    directory: Path = typer.Argument(..., metavar="DIR", help="Folder for the files."),
    hosts: str = typer.Option(
        ..., "--hosts", help="Machine ids, comma separated: registry,edge-1,robot-1,..."
    ),
    ip: list[str] | None = IP_OPTION,
    dns: list[str] | None = DNS_OPTION,
    days: int = DAYS_OPTION,
    force: bool = typer.Option(False, "--force", help="Replace an existing CA and certificates."),
) -> None:
    """A new fleet CA and a certificate per host (and the read-only `cli` one)."""
    from common.certs import init_fleet_certs, parse_host_values

    try:
        made = init_fleet_certs(
            directory,
            _hosts(hosts),
            ips=parse_host_values(ip or [], "--ip"),
            dns=parse_host_values(dns or [], "--dns"),
            days=days,
            force=force,
        )
    except UserError as exc:
        raise _fail(exc) from None
    for path in made:
        typer.echo(f"wrote {path}")
    typer.echo(f"keep {directory / 'ca.key'} off the hosts: it signs new certificates")


@certs_app.command("add")
def add(
    host: str = typer.Argument(..., metavar="HOST", help="The machine id (the common name)."),
    directory: Path = DIR_OPTION,
    ip: list[str] | None = IP_OPTION,
    dns: list[str] | None = DNS_OPTION,
    days: int = DAYS_OPTION,
    force: bool = typer.Option(False, "--force", help="Replace HOST's certificate (rotation)."),
) -> None:
    """A certificate for one more host (or a new one for HOST with --force), signed by DIR's CA."""
    from common.certs import SanSpec, issue, parse_host_values

    try:
        ips = parse_host_values(_for_host(ip or [], host), "--ip")
        names = parse_host_values(_for_host(dns or [], host), "--dns")
        other = sorted((set(ips) | set(names)) - {host})
        if other:
            raise UserError(f"--ip/--dns for {', '.join(other)}: this command adds {host} only")
        sans = SanSpec(extra_ips=tuple(ips.get(host, ())), extra_dns=tuple(names.get(host, ())))
        crt, key = issue(directory, host, sans=sans, days=days, force=force)
    except UserError as exc:
        raise _fail(exc) from None
    typer.echo(f"wrote {crt}")
    typer.echo(f"wrote {key}")


@certs_app.command("show")
def show(
    directory: Path = DIR_OPTION,
    as_json: bool = typer.Option(False, "--json", help="Print plain JSON on stdout."),
) -> None:
    """Every certificate of DIR: common name, expiry and SANs."""
    import datetime as dt

    from rich.console import Console
    from rich.table import Table

    from common.certs import show as show_certs

    try:
        infos = show_certs(directory)
    except UserError as exc:
        raise _fail(exc) from None
    if as_json:
        typer.echo(json.dumps([i.to_json() for i in infos], indent=2))
        return
    now = dt.datetime.now(dt.timezone.utc)
    table = Table(title=f"certificates in {directory}", title_justify="left", header_style="bold")
    for column in ("host", "common name", "expires", "SANs"):
        table.add_column(column)
    for i in infos:
        days_left = (i.not_after - now).days
        expires = f"{i.not_after:%Y-%m-%d} ({days_left} days)"
        if days_left < 0:
            expires = f"[red]{i.not_after:%Y-%m-%d} (expired)[/red]"
        elif days_left < 30:
            expires = f"[yellow]{expires}[/yellow]"
        sans = ", ".join([*i.ips, *i.dns]) or ("(CA)" if i.is_ca else "-")
        table.add_row(i.host, i.common_name, expires, sans)
    Console().print(table)
